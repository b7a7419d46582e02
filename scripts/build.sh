#!/usr/bin/env bash
# Configures and builds Amalgam (Release) into build/ (or $AMALGAM_BUILD_DIR). Extra arguments go
# to CMake, e.g. scripts/build.sh -DAMALGAM_REAL=double -DAMALGAM_NATIVE=ON
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
build="${AMALGAM_BUILD_DIR:-$root/build}"
gen=()
command -v ninja >/dev/null 2>&1 && gen=(-G Ninja)
if [ ! -f "$build/CMakeCache.txt" ]; then
  cmake -S "$root" -B "$build" "${gen[@]}" -DCMAKE_BUILD_TYPE=Release "$@"
elif [ $# -gt 0 ]; then
  cmake -S "$root" -B "$build" "$@"
fi
cmake --build "$build" --parallel "$(nproc)"
