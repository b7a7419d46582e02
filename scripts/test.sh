#!/usr/bin/env bash
# One command to run the tests: install dependencies if missing, build, run ctest (2 jobs).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/install_deps.sh"
"$root/scripts/build.sh"
cd "${AMALGAM_BUILD_DIR:-$root/build}"
ctest --output-on-failure -j2 "$@"
