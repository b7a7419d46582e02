#!/usr/bin/env bash
# Builds with AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/ and runs the test
# suite there, except the long end-to-end runs (axial-bar periods, material validation, the
# default scene, the SIGINT restart, the implicit physics runs and the peridynamics dynamics
# run, the A-ULMPM disc and bar runs), which take minutes each under ASan and exercise the same kernels and I/O code as the
# unit and CLI tests that do run. Any sanitizer report fails the test.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/install_deps.sh"
AMALGAM_BUILD_DIR="${AMALGAM_ASAN_DIR:-$root/build-asan}" "$root/scripts/build.sh" \
  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DAMALGAM_SANITIZE=address,undefined -DAMALGAM_BUILD_BENCH=OFF
cd "${AMALGAM_ASAN_DIR:-$root/build-asan}"
ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
  ctest --output-on-failure -j2 -E "AxialBar|MaterialValidation|default_scene|restart_after_sigint|ImplicitPhysics|PdDynamics|AulMpm.Spinning|AulMpm.Stretched" "$@"
