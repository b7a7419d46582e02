#!/usr/bin/env bash
# The one sanitizer build: clang, AddressSanitizer + UndefinedBehaviorSanitizer, and libFuzzer
# coverage in every library (AMALGAM_FUZZ), so the test suite (scripts/test_sanitizers.sh) and the
# libFuzzer targets (scripts/fuzz.sh) come out of the same build directory and CI compiles the
# code under sanitizers once, not twice (docs/testing.md, "CI time").
#   scripts/build_sanitized.sh DIR [TARGET ...]     configures DIR once, builds TARGETs (default: all)
# -O1 -g1 (line tables only): the heaviest translation unit (io/vdb_points.cpp, OpenVDB point
# conversion) compiles in about half the time of RelWithDebInfo's -O2 -g, and reports keep
# file:line stack traces. -DNDEBUG as in the release build (and the sanitizer suite before it
# shared this build; the fuzz-only build had assertions on). The gtest binaries whose every test the
# sanitizer suite leaves out (test_fidelity, test_validation, test_material_validation) are not
# built here (tests/CMakeLists.txt). Single-process (-DAMALGAM_MPI=OFF): OpenMPI's own
# allocations at start-up are reported as leaks; the distributed tests run in the release suite.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ $# -ge 1 ] || { echo "usage: build_sanitized.sh DIR [TARGET ...]" >&2; exit 2; }
build="$1"
shift
if [ -f "$build/CMakeCache.txt" ]; then
  grep -q '^AMALGAM_FUZZ:BOOL=ON$' "$build/CMakeCache.txt" \
    || { echo "build_sanitized.sh: $build was configured by an older script (no AMALGAM_FUZZ, maybe gcc): remove it" >&2; exit 2; }
else
  cmake -S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
        -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_C_COMPILER=clang "-DCMAKE_CXX_FLAGS_RELWITHDEBINFO=-O1 -g1 -DNDEBUG" \
        -DAMALGAM_FUZZ=ON -DAMALGAM_SANITIZE=address,undefined -DAMALGAM_BUILD_BENCH=OFF -DAMALGAM_MPI=OFF \
        -DAMALGAM_BUILD_TESTS=ON > /dev/null
fi
targets=()
[ $# -gt 0 ] && targets=(--target "$@")
cmake --build "$build" --parallel "$(nproc)" "${targets[@]}"
