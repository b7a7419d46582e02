#!/usr/bin/env python3
"""Google Benchmark JSON of build/bench/amalgam_microbench -> a Markdown table (ns per item).

One row per benchmark (name without its backend/threads arguments), one column per
configuration (serial 1, openmp 1/2, tbb 1/2, kokkos 1), each cell 1e9 / items_per_second of the
median repetition with the min-max of the repetitions in brackets; GB/s where the benchmark
counts bytes. Used by scripts/bench_report.sh for docs/bench_report/microbench.md.

    python3 bench/microbench_table.py RESULTS.json [--out microbench.md]
"""
import argparse
import collections
import json
import re

BACKENDS = {0: "serial", 1: "openmp", 2: "tbb", 3: "threads", 4: "kokkos"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("json")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    data = json.load(open(a.json))
    runs = collections.defaultdict(list)   # (bench, config) -> items/s of each repetition
    median = {}
    gbps = {}
    order, configs = [], []
    for b in data["benchmarks"]:
        name = b.get("run_name", b["name"])
        m = re.match(r"^(.*?)/backend:(\d+)/threads:(\d+)", name)
        if m:
            bench, cfg = m.group(1), (BACKENDS.get(int(m.group(2)), m.group(2)), int(m.group(3)))
        else:
            bench, cfg = re.sub(r"/real_time$", "", name), ("serial", 1)
        if bench not in order:
            order.append(bench)
        if cfg not in configs:
            configs.append(cfg)
        ips = b.get("items_per_second")
        if not ips:
            continue
        if b.get("run_type") == "aggregate":
            if b.get("aggregate_name") == "median":
                median[(bench, cfg)] = ips
                if b.get("bytes_per_second"):
                    gbps[(bench, cfg)] = b["bytes_per_second"] / 1e9
        else:
            runs[(bench, cfg)].append(ips)
    rank = {"serial": 0, "openmp": 1, "tbb": 2, "kokkos": 3, "threads": 4}
    configs.sort(key=lambda c: (rank.get(c[0], 9), c[1]))
    ctx = data["context"]
    lines = [
        "Microbenchmarks (`build/bench/amalgam_microbench`, Google Benchmark; %s, %d CPUs): ns per item "
        "= 1e9 / items_per_second, median of the repetitions [min-max]; items are particles, grid "
        "nodes, DOF-iterations, directed bonds, floats (STREAM) or flops (peak) as each benchmark's "
        "comment in bench/microbench.cpp says. GB/s (bytes each benchmark counts as streamed) "
        "below the table." % (ctx.get("date", "?"), ctx.get("num_cpus", 0)),
        "",
        "| benchmark | " + " | ".join("%s %d" % c for c in configs) + " |",
        "|---|" + "---:|" * len(configs),
    ]
    bw_rows = []
    for bench in order:
        cells, bw = [], []
        for cfg in configs:
            med = median.get((bench, cfg))
            if med is None and runs.get((bench, cfg)):
                med = sorted(runs[(bench, cfg)])[len(runs[(bench, cfg)]) // 2]
            if med is None:
                cells.append("")
                bw.append("")
                continue
            r = runs.get((bench, cfg), [])
            cell = "%.3g" % (1e9 / med)
            if len(r) > 1:
                cell += " [%.3g-%.3g]" % (1e9 / max(r), 1e9 / min(r))
            cells.append(cell)
            g = gbps.get((bench, cfg))
            bw.append("%.2f" % g if g else "")
        lines.append("| %s | %s |" % (bench, " | ".join(cells)))
        if any(bw):
            bw_rows.append("| %s | %s |" % (bench, " | ".join(bw)))
    if bw_rows:
        lines += ["", "GB/s:", "", "| benchmark | " + " | ".join("%s %d" % c for c in configs) + " |",
                  "|---|" + "---:|" * len(configs)] + bw_rows
    text = "\n".join(lines) + "\n"
    if a.out:
        with open(a.out, "w") as f:
            f.write(text)
    print(text)


if __name__ == "__main__":
    main()
