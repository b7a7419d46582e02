#!/usr/bin/env bash
# Distributed peridynamics (issue 28): the frames, samples and point files of a fracturing scene
# run on 1, 2, 3 and 4 MPI ranks (and 2 ranks x 2 threads) are bitwise those of the single
# process (also with a repartition forced every 7 steps; bonds break and fragments touch across
# the ranks' cuts, asserted from the run summary); a run checkpointed on 3 ranks resumes on 2 and on 1 and ends bitwise as the
# uninterrupted run; an interrupt under mpirun stops every rank with exit 130 and a checkpoint
# that resumes bitwise. (Distributed MPM: dist_mpm_test.sh.)
# RETRY_SCENE blows up in frame 2 at its cfl: on 2 ranks every rank retries the frame alike (the
# stability guard's verdict is reduced) and the samples and checkpoint are the single process's.
# Usage: dist_pd_test.sh AMALGAM MPIEXEC SCENE OUTDIR RETRY_SCENE
set -u
amalgam=$1 mpiexec=$2 scene=$3 out=$4 retry_scene=$5
source "$(dirname "$0")/dist_lib.sh"
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' || exit 1
[ "$(echo "$files" | wc -l)" -ge 14 ] || { echo "too few files in the reference run: $files"; exit 1; }
ranks_match || exit 1
# Forced repartitions (particles migrate with their rows every 7 steps) on 3 ranks, bitwise; its
# summary must show bonds broken between ranks, contacts across ranks and the repartitions.
AMALGAM_TEST_REPARTITION_EVERY=7 mpi 3 run "$scene" --threads 1 --out "$out/rep" >"$out/rep.log" 2>&1 ||
  { echo "run with forced repartitions failed"; tail "$out/rep.log"; exit 1; }
same "$out/rep" || exit 1
line=$(grep "amalgam: distributed:" "$out/rep.log")
echo "$line"
num() { echo "$line" | sed -n "s/.* \([0-9][0-9]*\) $1.*/\1/p"; }
[ "$(num 'repartitions')" -gt 5 ] 2>/dev/null || { echo "too few repartitions"; exit 1; }
[ "$(num 'directed bonds broken between ranks')" -gt 0 ] 2>/dev/null || { echo "no bond broke between ranks"; exit 1; }
[ "$(num "contacts with another rank")" -gt 0 ] 2>/dev/null || { echo "no contact across ranks"; exit 1; }
# The set-up builds each particle's bond row once, on its owner (plus a few rows of families'
# first members owned by another rank, for the families a rank holds or fits), not the whole list
# on every rank; each family of the surface correction is fitted on one rank, at most the mean.
fits=$(grep "amalgam: distributed set-up:" "$out/rep.log" | sed -n 's/.*; \([0-9]*\) families fitted over the ranks, at most \([0-9]*\) on a rank.*/\1 \2/p')
read -r fitted fitted_max <<<"$fits"
[ -n "$fitted" ] && [ "$fitted_max" -le $(((fitted + 2) / 3)) ] ||
  { echo "the families' fits are not spread over the 3 ranks: $fits"; exit 1; }
setup=$(grep "amalgam: distributed set-up:" "$out/rep.log")
echo "$setup"
built=$(echo "$setup" | sed -n 's/.*set-up: \([0-9]*\) bond rows built over the ranks for \([0-9]*\) particles (\([0-9]*\) of them.*/\1 \2 \3/p')
read -r rows_built particles family <<<"$built"
[ -n "$rows_built" ] && [ $((rows_built - family)) -eq "$particles" ] && [ $((4 * family)) -lt "$particles" ] ||
  { echo "the set-up built rows it does not need: $setup"; exit 1; }
resumes 3 3 2 0 || exit 1  # checkpoint on 3 ranks after frame 3, resumed on 2 and on 1
interrupted 4 150 3 || exit 1  # inside frame 4, on 4 ranks; resumed on 3
parts_match 2 3 || exit 1        # per-rank parts (owned particles), merged
parts_resumes 3 3 2 0 || exit 1  # per-rank checkpoint of 3 ranks resumed on 2 and 1
parts_resumes 0 3 4 || exit 1    # of one process (one part) resumed on 4 ranks
parts_resumes 2 3 3 || exit 1    # of 2 ranks resumed on 3
rm -rf "$out/retry1" "$out/retry2"
"$amalgam" run "$retry_scene" --threads 1 --out "$out/retry1" --quiet || { echo "retry scene failed"; exit 1; }
mpi 2 run "$retry_scene" --threads 1 --out "$out/retry2" >"$out/retry2.log" 2>&1 || { echo "retry scene failed on 2 ranks"; exit 1; }
grep -q "retrying frame 2" "$out/retry2.log" || { echo "no retry on 2 ranks"; exit 1; }
for f in samples.csv checkpoint.amck; do
  cmp -s "$out/retry1/$f" "$out/retry2/$f" || { echo "$f of the retried run differs on 2 ranks"; exit 1; }
done
echo "distributed peridynamics: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2 and 3->1 ranks and after an interrupt on 4; per-rank parts merged bitwise on 2 and 3 ranks and resumed 3->2, 3->1, 1->4, 2->3; a retried frame on 2 ranks"
