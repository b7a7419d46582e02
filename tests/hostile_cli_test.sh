#!/usr/bin/env bash
# Hostile conditions around `amalgam run`, each a reproducer from issue 26 that failed before:
# links planted in the output directory are never written through; two identical runs write
# byte-identical frames and checkpoints (VDB UUIDs derived, not random); a device, a directory or
# a repeated option is a clear error with the README's exit code; control characters from the
# input reach the terminal escaped; resuming a finished run says there is nothing to run.
# Usage: hostile_cli_test.sh AMALGAM SCENE OUTDIR
set -u
amalgam=$1 scene=$2 out=$3
rm -rf "$out"
mkdir -p "$out/a"
fail() { echo "FAIL: $*"; exit 1; }
run() { OMP_WAIT_POLICY=PASSIVE "$amalgam" run "$scene" --frames 2 --threads 2 --quiet "$@"; }

# 1. Symbolic links planted at frame, temporary and checkpoint names point at a file outside.
echo precious > "$out/victim"
for f in frame_0000.ply frame_0000.ply.tmp frame_0001.vdb frame_0001.vdb.tmp diagnostics.csv \
         diagnostics.csv.tmp checkpoint.amck checkpoint.amck.tmp; do
  ln -s "$out/victim" "$out/a/$f"
done
run --out "$out/a" || fail "run with planted links exited $?"
[ "$(cat "$out/victim")" = precious ] || fail "a planted link was written through"
[ -L "$out/a/frame_0000.ply" ] && fail "frame_0000.ply is still the planted link"

# 2. Byte-reproducible output: a second identical run writes the same bytes (diagnostics.csv
# holds wall times and is left out).
run --out "$out/b" || fail "second run exited $?"
for f in $(cd "$out/b" && find . -type f ! -name diagnostics.csv | sort); do
  cmp -s "$out/a/$f" "$out/b/$f" || fail "$f differs between two identical runs"
done

# 3. Exit codes and messages.
expect() {  # expect CODE REGEX COMMAND...
  local code=$1 re=$2
  shift 2
  local err
  err=$("$@" 2>&1 >/dev/null)
  local rc=$?
  [ $rc -eq "$code" ] || fail "'$*' exited $rc, expected $code: $err"
  echo "$err" | grep -qE "$re" || fail "'$*': message does not match '$re': $err"
}
expect 3 "/dev/zero: checkpoint is not a regular file" \
  "$amalgam" run "$scene" --out "$out/c" --resume /dev/zero --quiet
expect 3 "scene file is a directory" "$amalgam" run "$out" --out "$out/c" --quiet
expect 3 "scene file is a directory" "$amalgam" validate "$out"
expect 2 "option --threads given twice" "$amalgam" run "$scene" --threads 1 --threads 2
printf '{"simulation": {"dx": 0.1, "d\\u001b[31mx": 1}}' > "$out/escape.json"
expect 3 'd\\x1b\[31mx: unknown key' "$amalgam" validate "$out/escape.json"
err=$("$amalgam" validate "$out/escape.json" 2>&1)
case "$err" in *$'\033'*) fail "an escape character reached the terminal raw" ;; esac

# 4. Resuming a run that has reached its last frame.
msg=$(run --out "$out/a" --resume "$out/a/checkpoint.amck" 2>&1) || fail "resume of a finished run exited $?"
echo "$msg" | grep -q "nothing to run" || fail "resume of a finished run: $msg"
echo "hostile CLI cases: all held"
