#!/usr/bin/env bash
# Run-time vector width (core/exec/simd.hpp): short runs through the CLI write the same files, byte
# for byte, on every SIMD path this CPU runs (--simd baseline|avx2|avx512) -- an MPM scene with
# every kind of frame file, A-ULMPM with object contact, particle domains, a peridynamic bar with
# plasticity, fracture, fragment contact and a collider -- and a bad path is
# refused with exit 2. Paths the CPU lacks are skipped, saying so.
# Usage: simd_paths_test.sh AMALGAM DATA_DIR OUTDIR
set -u
amalgam=$1 data=$2 out=$3
fail() { echo "FAIL: $*"; exit 1; }
rm -rf "$out"
mkdir -p "$out"

"$amalgam" info --simd sse9 >"$out/bad.txt" 2>&1
[ $? -eq 2 ] || fail "--simd sse9 did not exit 2"
grep -q "unknown SIMD path 'sse9'" "$out/bad.txt" || fail "--simd sse9: $(cat "$out/bad.txt")"
AMALGAM_SIMD=sse9 "$amalgam" info >"$out/bad_env.txt" 2>&1
[ $? -eq 2 ] || fail "AMALGAM_SIMD=sse9 did not exit 2"
grep -q "AMALGAM_SIMD: unknown SIMD path 'sse9'" "$out/bad_env.txt" || fail "AMALGAM_SIMD=sse9: $(cat "$out/bad_env.txt")"

paths=()
for p in baseline avx2 avx512; do
  if "$amalgam" info --simd $p >"$out/info_$p.txt" 2>&1; then
    grep -q "^SIMD path: $p " "$out/info_$p.txt" || fail "info --simd $p does not name the path: $(cat "$out/info_$p.txt")"
    paths+=("$p")
  else
    echo "SIMD path $p: skipped ($(cat "$out/info_$p.txt"))"
  fi
done
[ "${paths[0]}" = baseline ] || fail "the baseline path does not run"
AMALGAM_SIMD=baseline "$amalgam" info | grep -q "^SIMD path: baseline " || fail "AMALGAM_SIMD=baseline ignored"

# scene, extra arguments; the baseline at 1 thread is the reference, the other paths at 2 TBB
# threads (TBB: OpenMP workers spin, slow on a loaded machine).
check() {
  local name=$1 scene=$2
  shift 2
  "$amalgam" run "$scene" --simd baseline --threads 1 --out "$out/$name/baseline" --quiet "$@" \
    || fail "$name: baseline run failed"
  local ref
  ref=$(cd "$out/$name/baseline" && find . -type f ! -name diagnostics.csv | sort)
  for p in "${paths[@]:1}"; do
    "$amalgam" run "$scene" --simd $p --backend tbb --threads 2 --out "$out/$name/$p" --quiet "$@" || fail "$name: $p run failed"
    local files n=0
    files=$(cd "$out/$name/$p" && find . -type f ! -name diagnostics.csv | sort)
    [ "$files" = "$ref" ] || fail "$name: $p wrote other files"
    for f in $files; do
      cmp "$out/$name/baseline/$f" "$out/$name/$p/$f" || fail "$name: $f differs on $p"
      n=$((n + 1))
    done
    # diagnostics.csv: its simulation columns (energies, momentum, ...) are the same bits too;
    # from wall_s on it holds timings.
    local csv=diagnostics.csv w
    if [ -f "$out/$name/baseline/$csv" ]; then
      w=$(head -1 "$out/$name/baseline/$csv" | tr ',' '\n' | grep -n '^wall_s$' | cut -d: -f1)
      [ -n "$w" ] && [ "$w" -gt 2 ] || fail "$name: no wall_s column in $csv"
      cmp <(cut -d, -f1-$((w - 1)) "$out/$name/baseline/$csv") <(cut -d, -f1-$((w - 1)) "$out/$name/$p/$csv") \
        || fail "$name: the simulation columns of $csv differ on $p"
      n=$((n + 1))
    fi
    echo "$name: $p identical to baseline ($n files)"
  done
}
check mpm "$data/async_output.json" --frames 2
check aul "$data/aul_restart.json" --frames 2
check domains "$data/domain_restart.json" --frames 1
check pd "$data/pd_restart.json" --frames 4
[ ${#paths[@]} -gt 1 ] || { echo "only the baseline path runs on this CPU: nothing to compare"; exit 77; }
exit 0
