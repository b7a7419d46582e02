#!/usr/bin/env bash
# The parallel kernels' tests (exec, grid, transfers, backend determinism: every kernel of a
# substep, materials and colliders included; the A-ULMPM, object-contact, enriched-MPM and
# peridynamics backend tests: every kernel of those solvers) under ThreadSanitizer, in build-tsan/
# (RelWithDebInfo, -DAMALGAM_SANITIZE=thread). Debian's libgomp and libtbb are not instrumented,
# so TSan cannot see their barriers and reports their hand-offs as races; the tests therefore run
# the kernels on the serial and the std::thread backend (AMALGAM_TEST_BACKENDS=serial,threads),
# with the same chunking OpenMP and TBB use. Usage: scripts/test_tsan.sh [ctest args]
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
build="${AMALGAM_TSAN_BUILD_DIR:-$root/build-tsan}"
cmake -S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DAMALGAM_SANITIZE=thread \
  -DAMALGAM_BUILD_BENCH=OFF > /dev/null
cmake --build "$build" -j2 --target test_exec test_grid test_transfers test_backends test_aulmpm \
  test_object_contact test_particle_domains test_peridynamics
cd "$build"
TSAN_OPTIONS="halt_on_error=1 second_deadlock_stack=1 suppressions=$root/tests/tsan.supp" AMALGAM_TEST_BACKENDS=serial,threads \
  ctest --output-on-failure -j1 -R "^(Exec|Grid|Binning|Transfers|Mpm|BackendDeterminism)|^AllTransfers/KernelDeterminism|^AulMpm\.(BitwiseIdentical|SemiImplicitBitwise)|^ObjectContact\.Bitwise|^ParticleDomains\.Bitwise|^PdBackends\." "$@"
