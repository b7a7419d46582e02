#!/usr/bin/env bash
# Renders a surfaced Amalgam frame with Blender headless (Cycles on the CPU, no denoising: Debian's
# Blender 3.4.1 has no OpenImageDenoise). Each input becomes one panel of OUT.png, left to right:
# the particles (PLY points), the surfaced mesh (OBJ/PLY) and the `density` fog grid of the
# surfacing VDB. Install Blender with `scripts/install_deps.sh --render`.
#
# usage: scripts/render_blender.sh --out OUT.png [--points frame_NNNN.ply] [--mesh surfacing_NNNN.obj]
#          [--vdb surfacing_NNNN.vdb] [--size 320x240] [--samples 16] [--threads N]
#          [--camera x,y,z --look-at x,y,z --fov DEG] [--density D] [--point-radius R]
# Camera coordinates are the scene's (Y up), e.g. the scene's preview.camera; by default the
# camera looks at the inputs' bounds from the front right. --threads fixes Blender's render
# threads (default: all cores). Exit codes: 0 written, 1 render failed, 2 usage, 3 no blender.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
blender="${BLENDER:-blender}"
if [ "${1:-}" = "--help" ] || [ $# -eq 0 ]; then sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 2; fi
command -v "$blender" >/dev/null 2>&1 || { echo "render_blender.sh: '$blender' not found (scripts/install_deps.sh --render)" >&2; exit 3; }
for a in "$@"; do
  case "$a" in --points|--mesh|--vdb) want_file=1 ;; *) if [ "${want_file:-0}" = 1 ] && [ ! -s "$a" ]; then echo "render_blender.sh: $a: no such file" >&2; exit 2; fi; want_file=0 ;; esac
done
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! "$blender" -b --factory-startup -noaudio --python-exit-code 1 --python "$here/render_blender.py" -- "$@" >"$log" 2>&1; then
  cat "$log" >&2
  echo "render_blender.sh: blender failed" >&2
  exit 1
fi
grep "^render_blender.py: wrote" "$log" || { cat "$log" >&2; exit 1; }
