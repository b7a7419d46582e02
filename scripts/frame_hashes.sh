#!/usr/bin/env bash
# Hashes the first frames of every example scene, for refactors that must not change results:
#   scripts/frame_hashes.sh AMALGAM_BINARY OUT.tsv [FRAMES] [SCENE...]
# runs each scene (default: every scenes/*.json but the soak scene) for FRAMES frames (default 2)
# on Serial with 1 thread and on TBB with 2 threads, and writes one line per written frame file:
#   scene  backend  file  sha256
# Compare two binaries with `diff <(cut -f1-4 a.tsv) <(cut -f1-4 b.tsv)`. VDB files are hashed
# without their header UUID (derived from the file's bytes now, random before: comparable with old
# binaries; docs/architecture.md), every
# other file byte for byte. Meshes come from scripts/get_meshes.sh.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bin="$(realpath "$1")"
out="$(realpath -m "$2")"
frames="${3:-2}"
shift $(( $# >= 3 ? 3 : $# ))
scenes=("$@")
if [ ${#scenes[@]} -eq 0 ]; then
  for s in "$root"/scenes/*.json; do
    [ "$(basename "$s")" = soak_million.json ] || scenes+=("$s")
  done
fi
[ -f "$root/scenes/meshes/armadillo.off" ] || bash "$root/scripts/get_meshes.sh" >/dev/null
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
# A VDB file's bytes with the 16-byte UUID string after the header's version fields blanked: the
# header is magic (8) + file version (4) + library major/minor (8) + grid-offsets flag (1), then
# the UUID as 36 ASCII characters.
vdb_hash() { python3 - "$1" <<'PY'
import hashlib, sys
b = bytearray(open(sys.argv[1], 'rb').read())
b[21:21 + 36] = b'0' * 36
print(hashlib.sha256(b).hexdigest())
PY
}
: > "$out"
for s in "${scenes[@]}"; do
  name="$(basename "$s" .json)"
  for cfg in "serial 1" "tbb 2"; do
    set -- $cfg
    dir="$work/$name-$1"
    if ! OMP_WAIT_POLICY=PASSIVE "$bin" run "$s" --backend "$1" --threads "$2" --frames "$frames" \
         --out "$dir" --checkpoint-every 0 --quiet > "$work/log" 2>&1; then
      echo "frame_hashes.sh: $name ($1): run failed:" >&2; cat "$work/log" >&2
      printf '%s\t%s\t%s\t%s\n' "$name" "$1" "-" "RUN-FAILED" >> "$out"
      continue
    fi
    for f in $(cd "$dir" && ls | grep -vE '^(diagnostics\.csv|checkpoint\.amck|implicit_steps\.csv)$' | sort); do
      case "$f" in
        *.vdb) h="$(vdb_hash "$dir/$f")" ;;
        *) h="$(sha256sum "$dir/$f" | cut -d' ' -f1)" ;;
      esac
      printf '%s\t%s\t%s\t%s\n' "$name" "$1" "$f" "$h" >> "$out"
    done
    rm -rf "$dir"
  done
  echo "frame_hashes.sh: $name done" >&2
done
