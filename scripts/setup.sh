#!/usr/bin/env bash
# One command for a fresh machine: install the Debian packages, build, run the default scene.
# Output: frames in out/jelly_drop/ (PLY) plus out/jelly_drop/diagnostics.csv.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/install_deps.sh"
"$root/scripts/build.sh"
cd "$root"
"${AMALGAM_BUILD_DIR:-$root/build}/bin/amalgam" run scenes/jelly_drop.json --out out/jelly_drop
