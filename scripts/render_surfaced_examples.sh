#!/usr/bin/env bash
# The surfaced example previews in docs/images: runs each scene up to its preview frame (frames
# are deterministic: the same as in a full run) with its output.surfacing, and renders that
# frame's points, surfaced mesh and density VDB side by side with scripts/render_blender.sh from
# the scene's preview camera (CAMERA "scene") or framing the body (CAMERA "auto").
# Usage: scripts/render_surfaced_examples.sh [SCENE:FRAME:CAMERA ...]
# (default: dam_break:12:scene snowball_wall:3:auto). Needs a build and Blender
# (scripts/install_deps.sh --render).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
bin="${AMALGAM_BUILD_DIR:-$root/build}/bin/amalgam"
out="${AMALGAM_EXAMPLES_OUT:-$root/out/examples}"
threads="${THREADS:-2}"
jobs=("$@")
[ ${#jobs[@]} -eq 0 ] && jobs=(dam_break:12:scene snowball_wall:3:auto)
for job in "${jobs[@]}"; do
  IFS=: read -r s f camera <<<"$job"
  scene="$root/scenes/$s.json"
  rm -rf "${out:?}/$s"
  start=$(date +%s.%N)
  "$bin" run "$scene" --threads "$threads" --frames "$f" --out "$out/$s" --quiet --checkpoint-every 0
  end=$(date +%s.%N)
  n=$(printf '%04d' "$f")
  view=()
  if [ "${camera:-scene}" = scene ]; then  # the scene's preview camera (scene coordinates, Y up)
    read -r cam look fov < <(python3 -c '
import json, sys
c = json.load(open(sys.argv[1]))["preview"]["camera"]
print(",".join(map(str, c["position"])), ",".join(map(str, c["look_at"])), c.get("fov_degrees", 40))' "$scene")
    view=(--camera "$cam" --look-at "$look" --fov "$fov")
  fi
  "$root/scripts/render_blender.sh" --points "$out/$s/frame_$n.ply" --mesh "$out/$s/surfacing_$n.ply" \
    --vdb "$out/$s/surfacing_$n.vdb" --out "$root/docs/images/${s}_surface.png" --size 320x240 \
    --samples 16 --threads "$threads" "${view[@]}"
  printf '%s: frames 0-%d simulated and surfaced in %.1f s on %s threads\n' "$s" "$f" \
    "$(awk "BEGIN{print $end - $start}")" "$threads"
done
