#!/usr/bin/env bash
# Asynchronous output (issue 32): runs written by the background writer and with --sync-output hold
# the same files, byte for byte, at 1 and 2 threads: every frame file (PLY, VDB points, grid
# volumes, surfacing VDB and mesh, previews, crack meshes), samples and checkpoints; only
# diagnostics.csv (wall times) differs. Usage: async_output_test.sh AMALGAM DATA_DIR OUTDIR
set -u
amalgam=$1 data=$2 out=$3
fail() { echo "FAIL: $*"; exit 1; }
rm -rf "$out"
# scene, extra arguments: an MPM scene with every kind of frame file, and peridynamics with crack
# meshes (surface_NNNN.obj). AMALGAM_ASYNC_TEST_THREADS (default "1 2"): the sanitizer suite
# (scripts/test_sanitizers.sh) runs 1 thread only, the same writer code at half the runs.
check() {
  local name=$1 scene=$2
  shift 2
  for t in ${AMALGAM_ASYNC_TEST_THREADS:-1 2}; do
    "$amalgam" run "$scene" --threads $t --out "$out/$name/async$t" --quiet "$@" || fail "$name: async run at $t threads failed"
    "$amalgam" run "$scene" --threads $t --out "$out/$name/sync$t" --quiet --sync-output "$@" \
      || fail "$name: --sync-output run at $t threads failed"
    local a s
    a=$(cd "$out/$name/async$t" && find . -type f ! -name diagnostics.csv | sort)
    s=$(cd "$out/$name/sync$t" && find . -type f ! -name diagnostics.csv | sort)
    [ "$a" = "$s" ] || fail "$name: different files at $t threads:"$'\n'"$a"$'\n'"---"$'\n'"$s"
    local n=0
    for f in $a; do
      cmp "$out/$name/async$t/$f" "$out/$name/sync$t/$f" || fail "$name: $f differs at $t threads"
      n=$((n + 1))
    done
    echo "$name, $t threads: $n files identical"
  done
}
check mpm "$data/async_output.json" --preview --frames 2
ls "$out/mpm/async1/frame_0002.grid.vdb" "$out/mpm/async1/surfacing_0002.obj" "$out/mpm/async1/preview_0002.png" \
  "$out/mpm/async1/frame_0002.vdb" "$out/mpm/async1/frame_0002.ply" >/dev/null || fail "a kind of frame file is missing"
check pd "$data/pd_tet_restart.json" --frames 2
ls "$out/pd/async1/surface_0002.obj" >/dev/null || fail "no crack mesh written"
