#!/usr/bin/env bash
# Distributed peridynamics (issue 28): the frames, samples and point files of a fracturing scene
# run on 1, 2, 3 and 4 MPI ranks (and 2 ranks x 2 threads) are bitwise those of the single
# process; a run checkpointed on 3 ranks resumes on 2 and on 1 and ends bitwise as the
# uninterrupted run; an interrupt under mpirun stops every rank with exit 130 and a checkpoint
# that resumes bitwise. (Distributed MPM: dist_mpm_test.sh.)
# Usage: dist_pd_test.sh AMALGAM MPIEXEC SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 scene=$3 out=$4
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_rmaps_base_oversubscribe=1
mpi() { local np=$1; shift; timeout 300 "$mpiexec" --oversubscribe -np "$np" "$amalgam" "$@"; }
rm -rf "$out"
"$amalgam" run "$scene" --threads 1 --out "$out/ref" --quiet || { echo "single-process run failed"; exit 1; }
files=$(cd "$out/ref" && ls frame_*.ply frame_*.vdb samples.csv samples/*)
[ "$(echo "$files" | wc -l)" -ge 14 ] || { echo "too few files in the reference run: $files"; exit 1; }
same() {  # same DIR: every reference file bitwise equal in DIR
  for f in $files; do cmp -s "$out/ref/$f" "$1/$f" || { echo "$f differs in $1"; return 1; }; done
}
for np in 1 2 3 4; do
  mpi $np run "$scene" --threads 1 --out "$out/np$np" --quiet || { echo "run on $np ranks failed"; exit 1; }
  same "$out/np$np" || exit 1
done
mpi 2 run "$scene" --threads 2 --backend tbb --out "$out/np2t2" --quiet || { echo "2 x 2 failed"; exit 1; }
same "$out/np2t2" || exit 1
# Checkpoint on 3 ranks after frame 3, resume on 2 (and on 1) to the end.
mpi 3 run "$scene" --threads 1 --frames 3 --out "$out/r3" --quiet || { echo "3-rank part failed"; exit 1; }
cp -r "$out/r3" "$out/r1"
mpi 2 run "$scene" --threads 1 --out "$out/r3" --resume "$out/r3/checkpoint.amck" --quiet ||
  { echo "resume on 2 ranks failed"; exit 1; }
same "$out/r3" || exit 1
"$amalgam" run "$scene" --threads 1 --out "$out/r1" --resume "$out/r1/checkpoint.amck" --quiet ||
  { echo "resume on 1 process failed"; exit 1; }
same "$out/r1" || exit 1
# An interrupt inside frame 4 (the 150th substep), on 4 ranks: every rank stops, one checkpoint.
AMALGAM_TEST_SIGINT_AT_SUBSTEP=150 mpi 4 run "$scene" --threads 1 --out "$out/int" --quiet 2>/dev/null
rc=$?
[ $rc -eq 130 ] || { echo "interrupted run on 4 ranks exited $rc, expected 130"; exit 1; }
[ -f "$out/int/checkpoint.amck" ] || { echo "no checkpoint after the interrupt"; exit 1; }
ls "$out/int"/*.tmp >/dev/null 2>&1 && { echo "half-written files left"; exit 1; }
mpi 3 run "$scene" --threads 1 --out "$out/int" --resume "$out/int/checkpoint.amck" --quiet ||
  { echo "resume after the interrupt failed"; exit 1; }
same "$out/int" || exit 1
echo "distributed peridynamics: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2 and 3->1 ranks and after an interrupt on 4"
