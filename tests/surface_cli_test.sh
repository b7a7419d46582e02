#!/usr/bin/env bash
# output.surfacing and `amalgam surface`: a run writes surfacing_NNNN.vdb/.ply per frame;
# `amalgam surface` surfaces the run's frame_NNNN.vdb again, byte for byte the same with 1 and 2
# threads, with --frames, --help and the README's exit codes. Usage: surface_cli_test.sh AMALGAM
# SCENE OUTDIR
set -u
amalgam=$1 scene=$2 out=$3
fail() { echo "FAIL: $*"; exit 1; }
rm -rf "$out"
"$amalgam" run "$scene" --threads 2 --out "$out/run" --quiet || fail "run failed"
for f in 0 1 2; do
  for ext in vdb ply; do
    [ -s "$out/run/surfacing_000$f.$ext" ] || fail "run did not write surfacing_000$f.$ext"
  done
done
head -c 400 "$out/run/surfacing_0001.ply" | grep -aq "property float vx" || fail "PLY mesh without velocity"
ls "$out/run"/*.tmp >/dev/null 2>&1 && fail "temporary files left"

"$amalgam" surface --help | grep -q "usage: amalgam surface" || fail "--help"
# t1: one thread, one frame at a time; t2: two frames at once on one thread each (the default
# for --threads 2); t2k1: one frame at a time on two threads. The same bytes from each.
"$amalgam" surface "$out/run" --scene "$scene" --threads 1 --mesh obj --out "$out/t1" --quiet \
  || fail "surface --threads 1 failed"
"$amalgam" surface "$out/run" --scene "$scene" --threads 2 --mesh obj --out "$out/t2" > "$out/t2.log" \
  || fail "surface --threads 2 failed"
"$amalgam" surface "$out/run" --scene "$scene" --threads 2 --frames-at-once 1 --mesh obj --out "$out/t2k1" \
  --quiet || fail "surface --threads 2 --frames-at-once 1 failed"
for f in 0 1 2; do
  grep -q "^frame $f ($((f + 1))/3): " "$out/t2.log" || fail "no progress line for frame $f with 2 frames at once"
  for ext in vdb obj; do
    for d in t2 t2k1; do
      cmp "$out/t1/surfacing_000$f.$ext" "$out/$d/surfacing_000$f.$ext" \
        || fail "surfacing_000$f.$ext differs between t1 and $d"
    done
  done
done
grep -q "surfaced 3 frames" "$out/t2.log" || fail "no summary line"
"$amalgam" surface "$out/run" --frames 1-1 --method spheres --out "$out/one" > "$out/one.log" \
  || fail "surface --frames 1-1 failed"
grep -q "frame 1 (1/1)" "$out/one.log" || fail "no progress line for frame 1"
[ "$(ls "$out/one")" = "surfacing_0001.vdb" ] || fail "--frames 1-1 wrote $(ls "$out/one")"

"$amalgam" surface "$out/run" --voxel-size -1 >/dev/null 2>&1; rc=$?
[ $rc -eq 2 ] || fail "negative --voxel-size: exit $rc, expected 2"
"$amalgam" surface "$out/run" --frames-at-once 0 >/dev/null 2>&1; rc=$?
[ $rc -eq 2 ] || fail "--frames-at-once 0: exit $rc, expected 2"
"$amalgam" surface "$out/run" --filters blur 2>&1 | grep -q "unknown filter 'blur'" || fail "unknown filter message"
"$amalgam" surface "$out/run" --scene "$scene" --groups steel 2>&1 | grep -q 'unknown material "steel"' \
  || fail "unknown group message"
"$amalgam" surface "$out/no_such_run" >/dev/null 2>&1; rc=$?
[ $rc -eq 3 ] || fail "missing run directory: exit $rc, expected 3"
echo "surface CLI: run surfaces, amalgam surface identical on 1 and 2 threads, options and exit codes"
