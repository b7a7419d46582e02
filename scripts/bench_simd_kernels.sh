#!/usr/bin/env bash
# Kernel speed of each run-time SIMD path against the baseline, by CPU time (a shared machine
# takes the CPU away from a process; its CPU time is far less distorted than its wall time):
# amalgam_microbench's serial MLS P2G and G2P and the grid update (2^18 particles of the standard
# sphere), the paths alternated in the same sitting (rotating which goes first), ROUNDS rounds;
# prints the median CPU ms per call of each path and the median [min, max] over rounds of each
# round's baseline/path ratio. Usage: scripts/bench_simd_kernels.sh MICROBENCH [ROUNDS] [PATHS]
set -euo pipefail
micro=$1 rounds=${2:-7} paths=(${3:-baseline avx2 avx512})
log=$(mktemp)
filter='BM_(P2G|G2P)/mls_quadratic/backend:0/|BM_GridUpdate/backend:0/'
for r in $(seq 1 "$rounds"); do
  echo "# round $r load: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
  n=${#paths[@]}
  for i in $(seq 0 $((n - 1))); do
    p=${paths[$(((i + r) % n))]}
    AMALGAM_SIMD=$p "$micro" --benchmark_filter="$filter" --benchmark_format=json 2>/dev/null |
      python3 -c "import json,sys
for b in json.load(sys.stdin)['benchmarks']: print('$r', '$p', b['name'].split('/')[0], b['cpu_time'])" >>"$log"
  done
done
python3 - "$log" "${paths[@]}" <<'PY'
import statistics, sys
log, paths = sys.argv[1], sys.argv[2:]
rows = [l.split() for l in open(log)]
for k in sorted({r[2] for r in rows}):
    t = {(r[0], r[1]): float(r[3]) for r in rows if r[2] == k}
    rounds = sorted({r for r, _ in t})
    out = []
    for p in paths:
        med = statistics.median(t[(r, p)] for r in rounds)
        q = [t[(r, paths[0])] / t[(r, p)] for r in rounds]
        out.append(f"{p} {med:.3f} ms (x{statistics.median(q):.3f} [{min(q):.3f}, {max(q):.3f}])")
    print(f"{k}, {len(rounds)} rounds, CPU time: " + "; ".join(out))
PY
rm -f "$log"
