#!/usr/bin/env bash
# Speed of each run-time SIMD path against the baseline (core/exec/simd.hpp): `amalgam bench`
# (10^6-particle MLS sphere) on TBB and OpenMP at 1 and 2 threads, the paths alternated in the same
# sitting (rotating which goes first), ROUNDS rounds; prints per configuration the median rate
# and P2G/G2P ns of each path, the median [min, max] over rounds of each round's ratio to the
# baseline, and the ratio of the best rounds (the least disturbed run of each path).
# The load average is printed per round (a shared machine distorts absolute numbers; ratios of
# neighbouring runs much less). Usage: scripts/bench_simd_paths.sh AMALGAM [ROUNDS] [PATHS]
set -euo pipefail
amalgam=$1 rounds=${2:-7} paths=(${3:-baseline avx2 avx512})
log=$(mktemp)
for r in $(seq 1 "$rounds"); do
  echo "# round $r load: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
  n=${#paths[@]}
  for i in $(seq 0 $((n - 1))); do
    p=${paths[$(((i + r) % n))]}
    "$amalgam" bench --simd "$p" --backends tbb,openmp --threads 1,2 --reps 1 |
      grep '^backend=' | sed "s/^/round=$r /" >>"$log"
  done
done
python3 - "$log" "${paths[@]}" <<'PY'
import re, statistics, sys
log, paths = sys.argv[1], sys.argv[2:]
rows = [dict(kv.split('=', 1) for kv in l.split()) for l in open(log)]
for cfg in sorted({(r['backend'], r['threads']) for r in rows}):
    sel = [r for r in rows if (r['backend'], r['threads']) == cfg]
    base = {r['round']: r for r in sel if r['simd'] == paths[0]}
    out = []
    for p in paths:
        rr = [r for r in sel if r['simd'] == p]
        rate = statistics.median(float(r['particle_substeps_per_s']) for r in rr)
        p2g = statistics.median(float(r['p2g_ns']) for r in rr)
        g2p = statistics.median(float(r['g2p_ns']) for r in rr)
        ratios = [float(r['particle_substeps_per_s']) / float(base[r['round']]['particle_substeps_per_s']) for r in rr]
        rp = [float(base[r['round']]['p2g_ns']) / float(r['p2g_ns']) for r in rr]
        rg = [float(base[r['round']]['g2p_ns']) / float(r['g2p_ns']) for r in rr]
        best = max(float(r['particle_substeps_per_s']) for r in rr) / max(float(r['particle_substeps_per_s']) for r in base.values())
        out.append(f"{p}: {rate:.3g} p-substeps/s (x{statistics.median(ratios):.3f} [{min(ratios):.3f}, {max(ratios):.3f}], best x{best:.3f}), "
                   f"P2G {p2g:.1f} ns (x{statistics.median(rp):.3f}), G2P {g2p:.1f} ns (x{statistics.median(rg):.3f})")
    print(f"{cfg[0]} {cfg[1]}T, {len(base)} rounds: " + "; ".join(out))
PY
rm -f "$log"
