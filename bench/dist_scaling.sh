#!/usr/bin/env bash
# Ranks against threads (issue 28), alternated in one sitting: PAIRS pairs of
#   amalgam run SCENE --threads R --backend BACKEND                      (1 rank x R threads)
#   mpirun --oversubscribe -np R amalgam run SCENE --threads 1 --backend BACKEND   (R ranks x 1)
# the order swapped every pair. Prints per run the process wall time, the frame loop's time
# (amalgam's "done" line), the communication line (bytes and messages per substep per rank, time
# in communication), the work per rank (the loop minus its exchanges, max/mean) and the
# distributed summary (repartitions, imbalance), then the medians and
# the ratio (1 x R time / R x 1 time: >= 1 means the ranks are at least as fast).
# Usage: bench/dist_scaling.sh AMALGAM SCENE RANKS PAIRS OUTDIR [BACKEND] [FRAMES]
# OpenMPI's MCA settings pass through the environment: on one node OMPI_MCA_pml=ob1 skips UCX's
# initialisation (MPI_Init ~0.4 -> ~0.15 s a rank, docs/scaling.md "Start-up and set-up"); say so
# with the results. Each log's "set-up, process start to frame loop" line splits the set-up.
set -u
amalgam=$1 scene=$2 ranks=$3 pairs=$4 out=$5 backend=${6:-tbb} frames=${7:-}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
mkdir -p "$out"
extra=""
[ -n "$frames" ] && extra="--frames $frames"
run() {  # mode (threads|ranks), tag; prints "tag wall loop" and the log's summary lines
  local mode=$1 tag=$2 t0 t1
  rm -rf "$out/run"
  t0=$(date +%s.%N)
  if [ "$mode" = threads ]; then
    "$amalgam" run "$scene" --threads "$ranks" --backend "$backend" --out "$out/run" $extra >"$out/$tag.log" 2>&1
  else
    mpirun --oversubscribe -np "$ranks" "$amalgam" run "$scene" --threads 1 --backend "$backend" \
      --out "$out/run" $extra >"$out/$tag.log" 2>&1
  fi || { echo "run failed: $tag"; tail "$out/$tag.log"; exit 1; }
  t1=$(date +%s.%N)
  local loop
  loop=$(sed -n 's/^amalgam: done: .*(\([0-9.e+-]*\) s).*/\1/p' "$out/$tag.log")
  echo "$tag $(echo "$t1 - $t0" | bc) $loop $(cut -d' ' -f1 /proc/loadavg)" >>"$out/times.txt"
  echo "$tag: whole $(echo "$t1 - $t0" | bc) s, loop $loop s, load $(cut -d' ' -f1 /proc/loadavg)"
  grep -E "^amalgam: (communication|distributed|work per rank)" "$out/$tag.log" | sed 's/^/    /'
}
rm -f "$out/times.txt"
for p in $(seq 1 "$pairs"); do
  if [ $((p % 2)) -eq 1 ]; then
    run threads "threads$p"; run ranks "ranks$p"
  else
    run ranks "ranks$p"; run threads "threads$p"
  fi
done
rm -rf "$out/run"
python3 - "$out/times.txt" "$ranks" <<'EOF'
import sys, statistics as st
rows = [l.split() for l in open(sys.argv[1])]
r = sys.argv[2]
def col(prefix, k): return [float(x[k]) for x in rows if x[0].startswith(prefix)]
for name, k in (("whole process", 1), ("frame loop", 2)):
    a, b = col("threads", k), col("ranks", k)
    ratios = [x / y for x, y in zip(a, b)]
    print(f"{name}: 1 x {r} threads median {st.median(a):.2f} s [{min(a):.2f}, {max(a):.2f}], "
          f"{r} ranks x 1 median {st.median(b):.2f} s [{min(b):.2f}, {max(b):.2f}]; "
          f"ratio per pair median {st.median(ratios):.3f} [{min(ratios):.3f}, {max(ratios):.3f}]")
EOF
