#!/usr/bin/env bash
# Distributed MPM features (issue 28), each bitwise against the single process on 1-4 ranks and 2
# ranks x 2 TBB threads, and resumed across rank counts:
#  - a field collider and grid volumes: a keyframed mesh plough (a lazily built level set, which
#    every rank builds around all ranks' particles) sweeps through snow and jelly; frames, samples,
#    grid volumes (every rank's owned leaves gathered to rank 0) and checkpoint; resumed 3 -> 2;
#  - sleeping: a sand bed falls asleep and a rock ball wakes part of it (every rank learns which
#    bins of the others rested); the sleeping counts of diagnostics.csv are not all 0 and equal on
#    3 ranks; resumed 3 -> 2.
# Usage: dist_features_test.sh AMALGAM MPIEXEC MESH_SCENE SLEEP_SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 mesh=$3 sleep_scene=$4 top=$5
source "$(dirname "$0")/dist_lib.sh"
scene=$mesh out=$top/mesh
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
echo "$files" | grep -q 'frame_0005.grid.vdb' || { echo "no grid volumes in the reference run"; exit 1; }
ranks_match || exit 1
resumes 3 2 2 || exit 1  # checkpoint on 3 ranks after frame 2, resumed on 2
echo "mesh collider and grid volumes: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2"
scene=$sleep_scene out=$top/sleep
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
ranks_match || exit 1
resumes 3 4 2 || exit 1
column() {  # the sleeping column of a run's diagnostics.csv
  awk -F, 'NR == 1 { for (i = 1; i <= NF; ++i) if ($i == "sleeping") c = i; next } { print $c }' "$1/diagnostics.csv"
}
s1=$(column "$out/ref") s3=$(column "$out/np3")
echo "sleeping particles per frame: $(echo $s1)"
echo "$s1" | grep -q '^[1-9]' || { echo "nothing fell asleep"; exit 1; }
[ "$s1" = "$s3" ] || { echo "sleeping counts differ on 3 ranks: $(echo $s3)"; exit 1; }
echo "sleeping: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2"
