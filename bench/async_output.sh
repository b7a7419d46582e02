#!/usr/bin/env bash
# Synchronous against asynchronous frame output (issue 32), alternated in one sitting:
# PAIRS pairs of `amalgam run SCENE --frames N --threads T`, one with --sync-output and one
# without, the order swapped every pair; prints per run the process wall time, the bytes written,
# the writer's seconds and the seconds the simulation was held (amalgam's "output" summary line)
# and the load average. Usage: bench/async_output.sh AMALGAM SCENE FRAMES THREADS PAIRS OUTDIR
set -u
amalgam=$1 scene=$2 frames=$3 threads=$4 pairs=$5 out=$6
mkdir -p "$out"
run() {  # mode (sync|async), tag
  local mode=$1 tag=$2 extra=""
  [ "$mode" = sync ] && extra=--sync-output
  rm -rf "$out/run"
  local t0 t1
  t0=$(date +%s.%N)
  "$amalgam" run "$scene" --frames "$frames" --threads "$threads" --out "$out/run" $extra > "$out/$tag.log" 2>&1 \
    || { echo "run failed: $tag"; tail "$out/$tag.log"; exit 1; }
  t1=$(date +%s.%N)
  local o
  o=$(grep "amalgam: output" "$out/$tag.log")
  echo "$tag wall_s=$(echo "$t1 - $t0" | bc) load=$(cut -d' ' -f1 /proc/loadavg) $o"
}
for p in $(seq 1 "$pairs"); do
  if [ $((p % 2)) -eq 1 ]; then
    run sync "sync$p"; run async "async$p"
  else
    run async "async$p"; run sync "sync$p"
  fi
done
rm -rf "$out/run"
