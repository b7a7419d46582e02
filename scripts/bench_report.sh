#!/usr/bin/env bash
# Regenerates the benchmark report (docs/bench_report/ by default): builds Amalgam if needed,
# runs the LAMMPS peer (bench/pd_peer.py, Debian's `lammps`, installed with apt-get when missing;
# --no-peer skips it), every Google Benchmark microbenchmark on every backend (JSON in
# DIR/microbench.json, table in DIR/microbench.md; --no-micro skips it), then
# `amalgam bench --report` twice (the first pass into DIR/previous/, the second compared with
# it: the report's repeatability section). report.md includes the peer and microbenchmark tables.
#
#   scripts/bench_report.sh [--out DIR] [--no-peer] [--no-micro] [--quick] [amalgam bench options...]
#
# --quick: a smoke run (scale 1/16, 2 repetitions, no peer, no microbenchmarks) into DIR, for
# checking the harness; the committed report uses the defaults: ~25 minutes on 2 cores.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="$root/docs/bench_report"
peer=1
micro=1
extra=()
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift 2 ;;
    --no-peer) peer=0; shift ;;
    --no-micro) micro=0; shift ;;
    --quick) extra+=(--scale 0.0625 --reps 2); peer=0; micro=0; shift ;;
    *) extra+=("$1"); shift ;;
  esac
done
build="${AMALGAM_BUILD_DIR:-$root/build}"
"$root/scripts/install_deps.sh"
"$root/scripts/build.sh"
amalgam="$build/bin/amalgam"
commit="$(git -C "$root" rev-parse --short HEAD 2>/dev/null || echo unknown)"
if [ -n "$(git -C "$root" status --porcelain --untracked-files=no 2>/dev/null)" ]; then commit="$commit (+ local changes)"; fi
mkdir -p "$out/previous"
rm -f "$out/peer_lammps.md" "$out/microbench.md" "$out/microbench.json"
if [ "$peer" = 1 ]; then
  if ! command -v lmp >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "bench_report.sh: installing Debian's lammps for the peer run"
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends lammps openmpi-bin >/dev/null
  fi
  python3 "$root/bench/pd_peer.py" --build "$build" --out "$out/peer_lammps.md"
fi
if [ "$micro" = 1 ]; then
  "$build/bench/amalgam_microbench" --benchmark_repetitions=3 --benchmark_min_time=0.2 \
    --benchmark_out="$out/microbench.json" --benchmark_out_format=json > /dev/null
  python3 "$root/bench/microbench_table.py" "$out/microbench.json" --out "$out/microbench.md" > /dev/null
fi
"$amalgam" bench --report "$out/previous" --commit "$commit" "${extra[@]}"
"$amalgam" bench --report "$out" --commit "$commit" --compare "$out/previous/results.csv" "${extra[@]}"
echo "bench_report.sh: $out/report.md"
