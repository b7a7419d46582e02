#!/usr/bin/env bash
# Resume is exact from any interrupt point: a run interrupted at many points (the first substep,
# inside frame 1, on the last substep of a frame, inside later frames, inside a retried frame, and
# during set-up) and resumed from its checkpoint writes every frame file bitwise as the
# uninterrupted run, never rewrites a frame written before the interrupt, and leaves no temporary
# file. Usage: interrupt_points_test.sh AMALGAM SCENE OUTDIR FRAMES
# The interrupt is injected at substep N (AMALGAM_TEST_SIGINT_AT_SUBSTEP, apps/frame_loop.cpp), so
# the points are exact whatever the machine's speed; the points are derived from the reference
# run's substeps per frame (diagnostics.csv).
set -u
amalgam=$1 scene=$2 out=$3 frames=$4
rm -rf "$out"
run() { OMP_WAIT_POLICY=PASSIVE "$amalgam" run "$scene" --frames "$frames" --threads 2 --quiet "$@"; }
run --out "$out/ref" || { echo "reference run failed"; exit 1; }
# Substeps per frame of the reference run (column "substeps"), and the retries it logged.
mapfile -t per_frame < <(awk -F, 'NR == 1 { for (i = 1; i <= NF; ++i) if ($i == "substeps") c = i; next } { print $c }' "$out/ref/diagnostics.csv")
[ "${#per_frame[@]}" -eq "$frames" ] || { echo "reference diagnostics has ${#per_frame[@]} rows, expected $frames"; exit 1; }
s1=${per_frame[0]} s2=${per_frame[1]}
# Samples (output.every_substeps): one row per sampled substep, steps strictly increasing (a
# retried frame's samples are removed with it).
if [ -f "$out/ref/samples.csv" ]; then
  awk -F, 'NR > 1 { if ($2 <= last) { print "samples.csv: step " $2 " after " last; bad = 1 } last = $2 } END { exit bad }' "$out/ref/samples.csv" \
    || { echo "samples.csv of the reference run repeats or reorders substeps"; exit 1; }
fi
points=(1 $(( (s1 + 1) / 2 )) "$s1" $(( s1 + 1 )) $(( s1 + (s2 + 1) / 2 )) $(( s1 + s2 )))
# A scene with a retried frame: also interrupt inside the retry (substeps of failed attempts count,
# so "total + 3" lands after the failure, in the retried attempt).
total=0
for s in "${per_frame[@]}"; do total=$(( total + s )); done
[ -n "${EXTRA_POINTS:-}" ] && points+=(${EXTRA_POINTS})
# AMALGAM_INTERRUPT_POINTS=few (the sanitizer suite, scripts/test_sanitizers.sh): the first substep,
# frame 1's last and the extra points only; the others run the same checkpoint and resume code again.
[ "${AMALGAM_INTERRUPT_POINTS:-all}" = few ] && points=(1 "$s1" ${EXTRA_POINTS:-})
# Frame and sample files; the logs (diagnostics, samples.csv, implicit steps) are cut back to the
# checkpoint on resume, so only their final contents are compared (below).
files() { (cd "$1" && find . -type f | sed 's|^\./||' | grep -vE '^(diagnostics\.csv|checkpoint\.amck|implicit_steps\.csv|samples\.csv)$' | sort); }
checked=0
for p in "${points[@]}"; do
  d="$out/at_$p"
  AMALGAM_TEST_SIGINT_AT_SUBSTEP=$p run --out "$d"
  rc=$?
  [ $rc -eq 130 ] || { echo "point $p: expected exit 130 after the injected SIGINT, got $rc"; exit 1; }
  [ -f "$d/checkpoint.amck" ] || { echo "point $p: no checkpoint"; exit 1; }
  ls "$d"/*.tmp >/dev/null 2>&1 && { echo "point $p: temporary files left: $(ls "$d"/*.tmp)"; exit 1; }
  # Frames written before the interrupt must not be written again: remember their inodes+mtimes.
  before=$(cd "$d" && for f in $(files .); do stat -c '%n %i %Y.%y' "$f"; done)
  run --out "$d" --resume "$d/checkpoint.amck" || { echo "point $p: resume failed"; exit 1; }
  for f in $(cd "$d" && echo "$before" | cut -d' ' -f1); do
    now=$(cd "$d" && stat -c '%n %i %Y.%y' "$f")
    echo "$before" | grep -qxF "$now" || { echo "point $p: $f was written again on resume"; exit 1; }
  done
  [ "$(files "$out/ref")" = "$(files "$d")" ] || { echo "point $p: the file lists differ"; diff <(files "$out/ref") <(files "$d"); exit 1; }
  for f in $(files "$out/ref"); do
    cmp -s "$out/ref/$f" "$d/$f" || { echo "point $p: $f differs from the uninterrupted run"; exit 1; }
  done
  if [ -f "$out/ref/samples.csv" ]; then
    cmp -s "$out/ref/samples.csv" "$d/samples.csv" || { echo "point $p: samples.csv differs from the uninterrupted run"; exit 1; }
  fi
  checked=$(( checked + 1 ))
done
# During set-up (injected once the simulation is built, AMALGAM_TEST_SIGINT_IN_SETUP): the
# process ends at once with a message, writes nothing and leaves no temporary file.
d="$out/setup"
AMALGAM_TEST_SIGINT_IN_SETUP=1 run --out "$d" 2> "$out/setup.err"
rc=$?
[ $rc -eq 130 ] || { echo "set-up interrupt: expected exit 130, got $rc"; cat "$out/setup.err"; exit 1; }
grep -q "interrupted during set-up" "$out/setup.err" || { echo "set-up interrupt: no message"; cat "$out/setup.err"; exit 1; }
[ -z "$(ls -A "$d")" ] || { echo "set-up interrupt: files written: $(ls "$d")"; exit 1; }
echo "interrupted at substeps ${points[*]} (of $total), resumed: every frame bitwise identical, none rewritten ($checked points); set-up interrupt exit $rc"
