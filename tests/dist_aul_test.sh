#!/usr/bin/env bash
# Distributed A-ULMPM (issue 28): a scene of three objects with their own configuration maps (an
# adaptive bar on a sticky collider, an Eulerian bar, a cube thrown against the first bar: contact
# between objects, separate with friction) runs on 1, 2, 3 and 4 MPI ranks (and 2 ranks x 2 TBB
# threads) bitwise as the single process: frames, samples and checkpoint; a checkpoint of 3 ranks
# resumes on 2 and on 1, a single-process one on 4, bitwise. The adaptive objects reset their
# configurations during the run and the contact corrects reference nodes, on every rank count the
# same number of times (run summary). A-ULMPM with PIC/FLIP and colliders is refused (exit 3).
# Usage: dist_aul_test.sh AMALGAM MPIEXEC SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 scene=$3 out=$4
source "$(dirname "$0")/dist_lib.sh"
reference 'frame_*.ply' 'frame_*.vdb' samples.csv 'samples/*' checkpoint.amck || exit 1
[ "$(echo "$files" | wc -l)" -ge 20 ] || { echo "too few files in the reference run: $files"; exit 1; }
ranks_match || exit 1
resumes 3 2 2 0 || exit 1  # checkpoint on 3 ranks after frame 2, resumed on 2 and on 1
resumes 0 3 4 || exit 1    # a single-process checkpoint after frame 3 resumed on 4 ranks
# Resets and contact happen, alike on one process and on 3 ranks (the summary's counts).
counts() { grep -E "configuration updates|velocity corrections" | sed 's/ in [0-9]* substeps.*//; s/ reference-node.*//'; }
one=$("$amalgam" run "$scene" --threads 1 --out "$out/sum1" 2>&1 | counts)
three=$(mpi 3 run "$scene" --threads 1 --out "$out/sum3" 2>&1 | counts)
echo "$one"
echo "$one" | grep -Eq "object 0 \(adaptive\): [1-9][0-9]* configuration updates" ||
  { echo "the adaptive bar never reset its configuration"; exit 1; }
echo "$one" | grep -Eq "friction 0.3\): [1-9]" || { echo "no contact between the objects"; exit 1; }
[ "$one" = "$three" ] || { echo "resets or contact differ on 3 ranks: $three"; exit 1; }
# A-ULMPM's PIC/FLIP node positions are not distributed: refused with the feature and key.
sed 's/"mls"/"flip"/' "$scene" >"$out/aul_pic_flip.json"
refused 2 "$out/aul_pic_flip.json" "$out/pf" 'PIC/FLIP transfers (simulation.transfer "pic" or "flip")' ||
  exit 1
echo "distributed A-ULMPM: $(echo "$files" | wc -l) files bitwise identical on 1-4 ranks, 2x2 threads, resumed 3->2, 3->1 and 1->4 ranks"
