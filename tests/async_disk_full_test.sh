#!/usr/bin/env bash
# A full disk during a background frame write (issue 32): the output directory is a small tmpfs
# (a real ENOSPC: mount needs root; the test is skipped, exit 77, where mounting is not allowed)
# holding about three frames. The run must stop with exit 3 (README: output not writable), the
# message naming the frame file that could not be written, leave no temporary file, and write no
# checkpoint (the final one would claim frames that are not on disk).
# Usage: async_disk_full_test.sh AMALGAM SCENE OUTDIR
set -u
amalgam=$1 scene=$2 out=$3
fail() { echo "FAIL: $*"; exit 1; }
rm -rf "$out"
mkdir -p "$out/ref" "$out/mnt"
"$amalgam" run "$scene" --threads 2 --out "$out/ref" --quiet || fail "reference run failed"
# Room for frames 0-2 (tmpfs counts whole 4 KiB pages), frame 3's PLY and half its VDB points:
# the disk fills up inside OpenVDB's write of frame_0003.vdb.
pages=$((($(stat -c %s "$out/ref/frame_0003.vdb") / 2 + 4095) / 4096))
for f in "$out/ref"/frame_000[0-2].* "$out/ref"/frame_0003.ply; do
  pages=$((pages + ($(stat -c %s "$f") + 4095) / 4096))
done
mount -t tmpfs -o size=$((pages * 4))k tmpfs "$out/mnt" 2>/dev/null || { echo "SKIP: cannot mount a tmpfs here"; exit 77; }
trap 'umount "$out/mnt"' EXIT
"$amalgam" run "$scene" --threads 2 --out "$out/mnt/run" --quiet 2> "$out/err.txt"
rc=$?
cat "$out/err.txt"
[ $rc -eq 3 ] || fail "expected exit 3 on a full disk, got $rc"
grep -q "frame_0003.vdb: cannot write VDB points" "$out/err.txt" \
  || fail "the message does not name the frame file and the error"
ls "$out/mnt/run"/*.tmp >/dev/null 2>&1 && fail "temporary files left on the full disk"
[ -e "$out/mnt/run/checkpoint.amck" ] && fail "a checkpoint was written although a frame was not"
bad=$(grep -Eo "frame_000[0-9]" "$out/err.txt" | head -1)
for f in "$out/mnt/run"/frame_*; do  # every frame file left is complete
  cmp "$f" "$out/ref/$(basename "$f")" || fail "$(basename "$f") left on the full disk is not the reference's"
done
echo "full disk: exit 3 naming $bad, no checkpoint, no temporary file, the frames left complete"
