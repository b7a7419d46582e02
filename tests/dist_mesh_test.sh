#!/usr/bin/env bash
# Distributed MPM with a field collider and grid volumes (issue 28): a keyframed mesh plough (a
# lazily built level set, which every rank builds around all ranks' particles) sweeps through a
# snow block and a jelly ball; frames, samples, grid volumes (every rank's owned leaves gathered
# to rank 0) and the checkpoint are bitwise the single process's on 1-4 ranks and 2 ranks x 2
# TBB threads, and a checkpoint of 3 ranks resumes on 2 bitwise.
# Usage: dist_mesh_test.sh AMALGAM MPIEXEC SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 scene=$3 out=$4
source "$(dirname "$0")/dist_lib.sh"
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
echo "$files" | grep -q 'frame_0005.grid.vdb' || { echo "no grid volumes in the reference run"; exit 1; }
ranks_match || exit 1
resumes 3 2 2 || exit 1  # checkpoint on 3 ranks after frame 2, resumed on 2
echo "distributed MPM with a mesh collider and grid volumes: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2"
