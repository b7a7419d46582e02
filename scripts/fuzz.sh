#!/usr/bin/env bash
# Builds the libFuzzer targets (clang, ASan + UBSan, coverage in every library:
# scripts/build_sanitized.sh) into build-fuzz/ (or $AMALGAM_FUZZ_DIR: CI points it at the
# sanitizer suite's build-asan/, which already holds them) and runs each for SECONDS (default 60)
# on its seed corpus, one after another:
#   scripts/fuzz.sh [SECONDS] [fuzz_scene|fuzz_mesh|fuzz_checkpoint ...]
# Limits per input, as docs/fuzzing.md states them: 1 MB long, 10 s, 1 GB of memory; any crash,
# sanitizer report, timeout or memory overrun fails the run (exit non-zero) and leaves the input
# in build-fuzz/findings/. Corpora grow in build-fuzz/corpus/TARGET (kept between runs). The inputs
# of past findings (tests/fuzz/regressions/TARGET) are replayed first. AMALGAM_FUZZ_JOBS=N runs up to
# N targets at once (default 1; CI: 2, one per core, as libFuzzer runs one thread: each target
# still gets its SECONDS of a whole core, and the three take two rounds instead of three).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
secs="${1:-60}"
shift $(( $# > 0 ? 1 : 0 ))
targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(fuzz_scene fuzz_mesh fuzz_checkpoint)
build="${AMALGAM_FUZZ_DIR:-$root/build-fuzz}"
"$root/scripts/install_deps.sh"
"$root/scripts/build_sanitized.sh" "$build" "${targets[@]}"
mkdir -p "$build/findings"
seed() {  # seed TARGET: the corpus directory, seeded once
  local dir="$build/corpus/$1"
  [ -d "$dir" ] && { echo "$dir"; return; }
  mkdir -p "$dir"
  case "$1" in
    fuzz_scene)
      cp "$root"/scenes/*.json "$root"/tests/data/*.json "$root"/tests/data/malformed/*.json \
         "$root"/tests/data/refused/*.json "$dir"/ ;;
    fuzz_mesh)  # first byte: 0 obj, 1 off, 2 ply, 3 stl
      local i=0
      for f in "$root"/tests/data/*.off "$root"/tests/data/malformed/*.off; do
        { printf '\001'; cat "$f"; } > "$dir/off_$i"; i=$((i + 1))
      done
      printf '\000v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n' > "$dir/obj_0"
      printf '\002ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n' > "$dir/ply_0"
      printf '\003solid t\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 0 1 0\nvertex 1 0 0\nendloop\nendfacet\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 0 1\nendloop\nendfacet\nendsolid t\n' > "$dir/stl_0" ;;
    fuzz_checkpoint)  # real checkpoints of the target's five cases, written by the target itself
      local tmp
      tmp="$(mktemp -d)"
      for k in 0 1 2 3 4; do printf "\\$(printf '%03o' "$k")" > "$tmp/case_$k"; done
      FUZZ_CHECKPOINT_SEEDS="$dir" "$build/tests/$1" -runs=0 "$tmp" > /dev/null 2>&1 || true
      rm -rf "$tmp" ;;
  esac
  echo "$dir"
}
one() {  # one TARGET: replay its regressions, seed, fuzz; exit non-zero on any finding
  local t="$1" reg corpus dict
  # Every input a campaign found (tests/fuzz/regressions/TARGET) must pass first.
  reg="$root/tests/fuzz/regressions/$t"
  if [ -d "$reg" ] && [ -n "$(ls -A "$reg")" ]; then
    "$build/tests/$t" -timeout=10 -rss_limit_mb=1024 -malloc_limit_mb=1024 "$reg"/* \
        > "$build/$t.regressions.log" 2>&1 \
      || { echo "fuzz.sh: $t: a regression input fails again:"; tail -30 "$build/$t.regressions.log"; exit 1; }
    echo "fuzz.sh: $t: $(ls "$reg" | wc -l) regression input(s) pass"
  fi
  corpus="$(seed "$t")"
  dict=()
  [ "$t" = fuzz_scene ] && dict=(-dict="$root/tests/fuzz/json.dict")
  echo "fuzz.sh: $t for ${secs}s on $(ls "$corpus" | wc -l) seeds"
  "$build/tests/$t" "$corpus" "${dict[@]}" -max_total_time="$secs" -max_len=1048576 -len_control=0 -timeout=10 \
      -rss_limit_mb=1024 -malloc_limit_mb=1024 -artifact_prefix="$build/findings/$t-" -print_final_stats=1 \
      2> "$build/$t.log" || { echo "fuzz.sh: $t FAILED:"; tail -40 "$build/$t.log"; exit 1; }
  grep -E "^stat::number_of_executed_units|^stat::peak_rss_mb|cov:" "$build/$t.log" | tail -3 | sed "s/^/fuzz.sh: $t: /"
}
jobs="${AMALGAM_FUZZ_JOBS:-1}"
for t in "${targets[@]}"; do
  if [ "$jobs" -le 1 ]; then one "$t"; continue; fi
  while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do sleep 1; done
  rm -f "$build/$t.status"
  { rc=0; one "$t" || rc=$?; echo "$rc" > "$build/$t.status"; } &
done
wait
if [ "$jobs" -gt 1 ]; then
  for t in "${targets[@]}"; do
    [ "$(cat "$build/$t.status" 2>/dev/null)" = 0 ] || { echo "fuzz.sh: $t failed (above)"; exit 1; }
  done
fi
echo "fuzz.sh: ${#targets[@]} target(s), ${secs}s each: no crash, no report, no timeout, no memory overrun"
