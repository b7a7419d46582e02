#!/usr/bin/env bash
# Faults in distributed runs (issue 28, item 6), with per-rank output (--parts ranks): a rank that
# stops answering ends the job on the others' --comm-timeout (exit 1, the message names the
# waiting rank and what it waited in), and a rank killed with SIGKILL ends the job through the
# launcher, each well before the test's own `timeout`; in both cases the last per-rank checkpoint
# is complete and resumes on another rank count bitwise. A corrupt or missing checkpoint part is
# refused on resume with a message naming the file and the rank that wrote it (exit 3), and a
# blow-up on one rank names that rank (exit 1). A rank killed while a checkpoint is written leaves
# the previous checkpoint whole.
# Usage: dist_faults_test.sh AMALGAM MPIEXEC SCENE RETRY_SCENE OUTDIR
set -u
amalgam=$1 mpiexec=$2 scene=$3 retry=$4 out=$5
source "$(dirname "$0")/dist_lib.sh"
reference 'frame_*.ply' 'frame_*.vdb' checkpoint.amck || exit 1
# ends NAME LIMIT CMD...: runs CMD (its stderr to $out/NAME.err), sets rc and secs; fails when it
# took LIMIT seconds or more (the safety net, `timeout 120`, is far above every limit).
ends() {
  local name=$1 limit=$2
  shift 2
  local t0=$(date +%s.%N)
  timeout 120 "$@" >/dev/null 2>"$out/$name.err"
  rc=$?
  secs=$(echo "$(date +%s.%N) - $t0" | bc)
  [ "$rc" -ne 124 ] || { echo "$name: killed by the test's timeout (hang)"; return 1; }
  [ "$(echo "$secs < $limit" | bc)" -eq 1 ] || { echo "$name: took $secs s, limit $limit"; return 1; }
}
# resumable DIR NP: DIR's checkpoint is a complete manifest; resumed on NP ranks and merged, the
# run ends bitwise as the single process's.
resumable() {
  head -c 1 "$1/checkpoint.amck" | grep -q '{' || { echo "$1: no checkpoint manifest"; return 1; }
  ls "$1"/*.tmp >/dev/null 2>&1 && rm -f "$1"/*.tmp  # a killed rank's unfinished temporary file
  mpi "$2" run "$scene" --threads 1 --parts ranks --out "$1" --resume "$1/checkpoint.amck" --quiet ||
    { echo "$1: resume on $2 ranks failed"; return 1; }
  "$amalgam" merge "$1" >/dev/null || { echo "$1: merge failed"; return 1; }
  same "$1"
}
# A rank stops answering inside frame 3 (after the checkpoint of frame 2): the others wait 3 s.
AMALGAM_TEST_STALL_RANK=1:180 ends stall 60 "$mpiexec" --oversubscribe -np 3 "$amalgam" run "$scene" --threads 1 \
  --parts ranks --checkpoint-every 1 --comm-timeout 3 --out "$out/stall" --quiet || exit 1
[ $rc -eq 1 ] || { echo "stalled rank: exit $rc, expected 1"; cat "$out/stall.err"; exit 1; }
grep -q "amalgam: error: MPI rank [02] of 3: no answer in .* within 3 s (--comm-timeout): .*did not hear from rank 1\b" "$out/stall.err" ||
  { echo "stalled rank: no time-out message"; cat "$out/stall.err"; exit 1; }
stall_secs=$secs
resumable "$out/stall" 2 || exit 1
# A rank is killed (SIGKILL) inside frame 3: the launcher ends the job.
AMALGAM_TEST_STALL_RANK=2:180:kill ends kill 60 "$mpiexec" --oversubscribe -np 3 "$amalgam" run "$scene" --threads 1 \
  --parts ranks --checkpoint-every 1 --out "$out/kill" --quiet || exit 1
[ $rc -ne 0 ] || { echo "killed rank: the job exited 0"; exit 1; }
kill_secs=$secs
resumable "$out/kill" 3 || exit 1
# Rank 1 is killed while the checkpoint after frame 3 is written (its part on disk, no manifest
# yet): the checkpoint after frame 2 stays the valid one, and resumes bitwise.
AMALGAM_TEST_KILL_IN_CHECKPOINT=1:3 ends killck 60 "$mpiexec" --oversubscribe -np 3 "$amalgam" run "$scene" \
  --threads 1 --parts ranks --checkpoint-every 1 --out "$out/killck" --quiet || exit 1
[ $rc -ne 0 ] || { echo "killed in a checkpoint: the job exited 0"; exit 1; }
grep -q '"generation": 2' "$out/killck/checkpoint.amck" || { echo "killed in a checkpoint: the manifest is not generation 2"; exit 1; }
resumable "$out/killck" 2 || exit 1
# A per-rank checkpoint of 3 ranks with a corrupt part of rank 1, then a missing part of rank 2.
mpi 3 run "$scene" --threads 1 --parts ranks --frames 2 --out "$out/bad" --quiet || { echo "3-rank run failed"; exit 1; }
part1=$(cd "$out/bad" && ls checkpoint.g*.r001.amck) part2=$(cd "$out/bad" && ls checkpoint.g*.r002.amck)
rm -rf "$out/bad1" "$out/bad2" && cp -r "$out/bad" "$out/bad1" && cp -r "$out/bad" "$out/bad2"
printf '\x55' | dd of="$out/bad1/$part1" bs=1 seek=200 conv=notrunc status=none
ends corrupt 60 "$mpiexec" --oversubscribe -np 2 "$amalgam" run "$scene" --threads 1 --parts ranks --out "$out/bad1" --resume "$out/bad1/checkpoint.amck" --quiet || exit 1
[ $rc -eq 3 ] || { echo "corrupt part: exit $rc, expected 3"; cat "$out/corrupt.err"; exit 1; }
grep -q "$part1: does not match its manifest (size or checksum).*(checkpoint part of rank 1 of 3" "$out/corrupt.err" ||
  { echo "corrupt part: unclear message"; cat "$out/corrupt.err"; exit 1; }
rm "$out/bad2/$part2"
ends missing 60 "$mpiexec" --oversubscribe -np 2 "$amalgam" run "$scene" --threads 1 --parts ranks --out "$out/bad2" --resume "$out/bad2/checkpoint.amck" --quiet || exit 1
[ $rc -eq 3 ] || { echo "missing part: exit $rc, expected 3"; exit 1; }
grep -q "$part2.*(checkpoint part of rank 2 of 3" "$out/missing.err" || { echo "missing part: unclear message"; cat "$out/missing.err"; exit 1; }
# merge: a frame without its manifest is skipped with a note; a corrupt frame part is refused
# naming the file and the rank (exit 3).
rm -rf "$out/bad3" && cp -r "$out/bad" "$out/bad3" && rm "$out/bad3/frame_0002.manifest.json"
msg=$("$amalgam" merge "$out/bad3" 2>&1) || { echo "merge with an incomplete frame failed: $msg"; exit 1; }
echo "$msg" | grep -q "frame 2 has parts but no manifest (incomplete" || { echo "merge: no note of the incomplete frame: $msg"; exit 1; }
[ -f "$out/bad3/frame_0001.vdb" ] && [ ! -f "$out/bad3/frame_0002.vdb" ] || { echo "merge joined the wrong frames"; exit 1; }
printf '\x55' | dd of="$out/bad3/frame_0001.r002.pts" bs=1 seek=100 conv=notrunc status=none
msg=$("$amalgam" merge "$out/bad3" 2>&1)
rc=$?
[ $rc -eq 3 ] || { echo "merge of a corrupt part: exit $rc, expected 3"; exit 1; }
echo "$msg" | grep -q "frame_0001.r002.pts (part of rank 2): does not match the manifest" ||
  { echo "merge of a corrupt part: unclear message: $msg"; exit 1; }
# A blow-up on one rank names the particle and its rank.
mpi 3 run "$retry" --threads 1 --retries 0 --out "$out/blow" --quiet 2>"$out/blow.err"
rc=$?
[ $rc -eq 1 ] || { echo "blow-up: exit $rc, expected 1"; exit 1; }
grep -q "particle id [0-9]* (rank [0-2])" "$out/blow.err" || { echo "blow-up: rank not named"; cat "$out/blow.err"; exit 1; }
echo "distributed faults: a stalled rank ended the job in $stall_secs s (--comm-timeout 3), a killed rank in $kill_secs s; both checkpoints resumed bitwise (3->2, 3->3); a rank killed inside a checkpoint left the previous one, resumed bitwise; corrupt and missing parts refused naming file and rank (exit 3); merge skips an incomplete frame and refuses a corrupt part; a blow-up names its rank"
