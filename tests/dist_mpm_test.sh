#!/usr/bin/env bash
# Distributed explicit MPM (issue 28): the frames, samples and point files of a scene with two
# materials and analytic colliders run on 1, 2, 3 and 4 MPI ranks (and 2 ranks x 2 threads, and 3
# ranks repartitioning every 10 substeps) are bitwise those of the single process, and no rank
# holds more than half of the particles at set-up on 3 ranks (sampled in slices); a run
# checkpointed on 3 ranks resumes on 2 and on 1 (and a single-process checkpoint on 4 ranks) and
# ends bitwise as the uninterrupted run; an interrupt on 4 ranks stops every rank with exit 130 and
# a checkpoint that resumes bitwise on 3; a feature not distributed yet is refused (exit 3) with
# its name, before any frame is written; sorting every substep instead of only when needed (the
# default) is bitwise on 1-4 ranks too; a retried frame is retried on every rank alike; a scene
# with an emitter and a kill region runs bitwise on 1-4 ranks and resumes across rank counts.
# Usage: dist_mpm_test.sh AMALGAM MPIEXEC SCENE SOURCES_SCENE RETRY_SCENE IMPLICIT_SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 scene=$3 sources=$4 retry=$5 implicit=$6 out=$7
source "$(dirname "$0")/dist_lib.sh"
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
[ "$(echo "$files" | wc -l)" -ge 20 ] || { echo "too few files in the reference run: $files"; exit 1; }
ranks_match || exit 1
# Repartitions with migration every 10 substeps (test hook): the same files.
AMALGAM_TEST_REPARTITION_EVERY=10 mpi 3 run "$scene" --threads 1 --out "$out/rep" >"$out/rep.log" ||
  { cat "$out/rep.log"; echo "repartitioning run failed"; exit 1; }
same "$out/rep" || exit 1
# The set-up is sampled in slices, one per rank: no rank held more than about a third of the
# particles (a whole set-up on every rank would hold all of them).
setup=$(grep -o 'set-up: at most [0-9]* of [0-9]* particles' "$out/rep.log") ||
  { cat "$out/rep.log"; echo "no set-up line in the summary"; exit 1; }
read -r most total < <(echo "$setup" | awk '{print $4, $6}')
[ "$total" -gt 1000 ] && [ $((most * 2)) -lt "$total" ] ||
  { echo "set-up on 3 ranks: $setup (expected at most half on one rank)"; exit 1; }
# The set-up's phases are timed on every rank (least / most of the ranks), the split included.
grep -Eq '^amalgam: set-up, process start to frame loop \(s; least / most of 3 ranks\): [0-9.]+ / [0-9.]+ \(CPU [0-9.]+ / [0-9.]+\) = .*mpi_init [0-9.]+ / [0-9.]+,.* begin_run [0-9.]+ / [0-9.]+' "$out/rep.log" ||
  { grep "set-up" "$out/rep.log"; echo "no timed set-up line on 3 ranks"; exit 1; }
resumes 3 2 2 0 || exit 1  # checkpoint on 3 ranks after frame 2, resumed on 2 and on 1
resumes 0 3 4 || exit 1    # a single-process checkpoint after frame 3 resumed on 4 ranks
interrupted 4 150 3 || exit 1  # inside frame 3, on 4 ranks; resumed on 3
parts_match 2 3 || exit 1     # per-rank parts, merged (frames and checkpoint)
parts_resumes 3 2 2 0 || exit 1  # per-rank checkpoint of 3 ranks resumed on 2 and 1
parts_resumes 0 3 4 || exit 1    # of one process (one part) resumed on 4 ranks
parts_resumes 2 2 3 || exit 1    # of 2 ranks resumed on 3
# A hostile per-rank checkpoint: part 1 repeats one of part 0's ids, every checksum made consistent
# (tests/dup_part_id.py), so only the ids' check across the parts can find it: refused with exit 3
# on 1, 2 and 3 ranks before any frame is written.
for np in 0 2 3; do
  python3 "$(dirname "$0")/dup_part_id.py" "$out/pc2" "$out/dup$np" >/dev/null ||
    { echo "could not write the hostile checkpoint"; exit 1; }
  msg=$(mpi $np run "$scene" --threads 1 --parts ranks --out "$out/dup$np" --resume "$out/dup$np/checkpoint.amck" --quiet 2>&1)
  rc=$?
  [ $rc -eq 3 ] && echo "$msg" | grep -q "attribute 'id'.*repeats" ||
    { echo "repeated id across parts on $np ranks: exit $rc, $msg"; exit 1; }
  ls "$out/dup$np"/frame_0003* >/dev/null 2>&1 && { echo "frames written after a hostile checkpoint"; exit 1; }
done
parts_interrupted 3 150 2 || exit 1  # SIGINT inside frame 3 on 3 ranks; resumed on 2
all=$(echo "$files" | wc -l)
# Emitters and a kill region: every rank emits alike and keeps what lands in its leaves; the
# kill counts are summed over the ranks.
top=$out scene=$sources out=$top/sources
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
ranks_match || exit 1
resumes 3 2 2 0 || exit 1
parts_match 3 || exit 1  # emitted particles keyed after the sorted ones, by id
parts_resumes 3 2 2 || exit 1
out=$top
# A frame that blows up is retried from its start on every rank at once (the guard is reduced):
# the retried run's final checkpoint is bitwise the single process's.
"$amalgam" run "$retry" --threads 1 --out "$out/retry1" --quiet 2>"$out/retry1.err" ||
  { echo "single-process retry run failed"; exit 1; }
mpi 3 run "$retry" --threads 1 --out "$out/retry3" --quiet 2>"$out/retry3.err" ||
  { echo "retry run on 3 ranks failed"; exit 1; }
grep -q "retrying frame" "$out/retry3.err" || { echo "no retry on 3 ranks"; exit 1; }
cmp -s "$out/retry1/checkpoint.amck" "$out/retry3/checkpoint.amck" ||
  { echo "retried run on 3 ranks differs"; exit 1; }
# Implicit MPM is not distributed yet: a clear refusal naming it (exit 3), no frame written.
refused 2 "$implicit" "$out/imp" "implicit integration (simulation.implicit) is not distributed yet" ||
  exit 1
# The fused substep rounds its grid sums otherwise than the two passes: on several ranks it is
# refused (one rank runs it like the single process), so no run's bits depend on the rank count.
sed 's/"simulation": *{/"simulation": {"transfer_pass": "fused", /' "$scene" >"$out/fused.json"
grep -q '"transfer_pass": "fused"' "$out/fused.json" || { echo "could not make the fused scene"; exit 1; }
refused 2 "$out/fused.json" "$out/fu" 'fused G2P2G substep (simulation.transfer_pass "fused") is not distributed yet' ||
  exit 1
# The runs above re-sort only when needed (the default, solvers/mpm_lazy_distributed.cpp); the
# same scene sorted every substep (the plan of solvers/mpm_distributed.cpp, every substep) is
# bitwise on 1-4 ranks too, and differs from the default (rounding: another summation order).
top=$out sources_files=$files
sed 's/"simulation": *{/"simulation": {"sort": "every_substep", /' "$scene" >"$top/every.json"
grep -q '"sort": "every_substep"' "$top/every.json" || { echo "could not make the every-substep scene"; exit 1; }
scene=$top/every.json out=$top/every
reference 'frame_*.ply' 'frame_*.vdb' checkpoint.amck || exit 1
ranks_match || exit 1
cmp -s "$top/ref/checkpoint.amck" "$out/ref/checkpoint.amck" &&
  { echo "sorting every substep gave the default's bits: the default did not re-sort only when needed"; exit 1; }
out=$top files=$sources_files
echo "distributed MPM: $all files bitwise identical on 1-4 ranks, 2x2 threads, with repartitions, resumed 3->2, 3->1 and 1->4 ranks and after an interrupt on 4; per-rank parts (--parts ranks) merged bitwise on 2 and 3 ranks and resumed 3->2, 3->1, 1->4, 2->3 and after an interrupt 3->2; with emitters and a kill region $(echo "$files" | wc -l) files on 1-4 ranks, 2x2 threads, resumed 3->2 and 3->1; sorted every substep: bitwise on 1-4 ranks and 2x2 threads"
