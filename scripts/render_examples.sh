#!/usr/bin/env bash
# Runs example scenes with --preview, prints wall time and peak memory per scene, and copies
# the last frame's preview to docs/images/SCENE.png. Usage: scripts/render_examples.sh [SCENE...]
# (default: every scene in scenes/). Needs a build (scripts/build.sh) and, for mesh scenes,
# scripts/get_meshes.sh.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
bin="${AMALGAM_BUILD_DIR:-$root/build}/bin/amalgam"
out="${AMALGAM_EXAMPLES_OUT:-$root/out/examples}"
mkdir -p "$root/docs/images"
scenes=("$@")
if [ ${#scenes[@]} -eq 0 ]; then
  for f in "$root"/scenes/*.json; do case "$(basename "$f")" in soak_*) ;; *) scenes+=("$(basename "$f" .json)") ;; esac; done
fi
for s in "${scenes[@]}"; do
  rm -rf "${out:?}/$s"
  start=$(date +%s.%N)
  /usr/bin/time -f "%M" -o "$out.$s.mem" "$bin" run "$root/scenes/$s.json" --preview --quiet --out "$out/$s" \
    --checkpoint-every 0 || { echo "$s: FAILED"; continue; }
  end=$(date +%s.%N)
  last=$(ls "$out/$s"/preview_*.png | tail -1)
  cp "$last" "$root/docs/images/$s.png"
  printf '%s: %.1f s wall, peak RSS %d MB, %s\n' "$s" "$(awk "BEGIN{print $end - $start}")" \
    "$(( $(cat "$out.$s.mem") / 1024 ))" "$(basename "$last")"
  rm -f "$out.$s.mem"
done
