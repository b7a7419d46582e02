#!/usr/bin/env bash
# Builds with AddressSanitizer + UndefinedBehaviorSanitizer into build-asan/ and runs the test
# suite there, except the long end-to-end and validation runs (axial-bar periods, material
# validation, the default scene, the SIGINT and tet-mesh restarts, the implicit physics runs and
# the CLI implicit scene, the peridynamics dynamics, moduli, homogeneous-deformation, hydrostatic
# plasticity and bar-validation runs, the A-ULMPM disc, bar, twisted-bar and semi-implicit
# physics runs, the enriched-MPM twisted-bar, stretched-bar and implicit-vs-explicit runs, the
# interrupt-point runs but the peridynamic retry, the fused-substep one included: its kernel runs
# here in G2P2G*.*, its checkpoint and resume code is the two-pass one's), which take half a minute to two minutes each under ASan and exercise the
# same kernels and I/O code as the unit and CLI tests that do run. Also out: the bitwise
# comparisons whose runs repeat kernels other tests here already run (cli.simd_paths_bitwise: the
# CLI on every SIMD path, whose kernels SimdPaths.* and PdSimdPaths.* run on every path here;
# BackendDeterminism.ImplicitBitwiseIdentical: the implicit step, which
# SimdPaths.MaterialsAndImplicitBitwiseOnEveryPath runs here), and the peridynamic retry's
# interrupt points are cut to the first substep, frame 1's last and the two inside the failed
# attempt and its retry (AMALGAM_INTERRUPT_POINTS=few), and cli.async_output_identical_to_sync
# compares at 1 thread only (AMALGAM_ASYNC_TEST_THREADS=1: the same writer code; the 2-thread
# comparison is determinism, the release suite's). Any sanitizer report fails the test. The backend tests run Serial and OpenMP only here (AMALGAM_TEST_BACKENDS; override
# by setting it): the bitwise comparisons across every backend are the release suite's job, and
# TBB and Kokkos call the same kernel bodies, so under ASan they add time, not coverage of our
# code. The build is scripts/build_sanitized.sh's (clang, single-process, with the libFuzzer
# targets in it, which scripts/fuzz.sh then runs from the same directory: .ci/run).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/install_deps.sh"
"$root/scripts/build_sanitized.sh" "${AMALGAM_ASAN_DIR:-$root/build-asan}"
cd "${AMALGAM_ASAN_DIR:-$root/build-asan}"
AMALGAM_TEST_BACKENDS="${AMALGAM_TEST_BACKENDS:-serial,openmp}" AMALGAM_INTERRUPT_POINTS="${AMALGAM_INTERRUPT_POINTS:-few}" \
AMALGAM_ASYNC_TEST_THREADS="${AMALGAM_ASYNC_TEST_THREADS:-1}" \
LSAN_OPTIONS="suppressions=$root/tests/lsan.supp" ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
  ctest --output-on-failure -j2 -E "AxialBar|MaterialValidation|Fidelity|default_scene|restart_after_sigint|ImplicitPhysics|PdDynamics|AulMpm.Spinning|AulMpm.FastSpinning|AulMpm.Stretched|AulMpm.Twisted|AulMpm.SemiImplicitLagrangian|ObjectContact.HeadOn|ObjectContact.Sliding|PdValidation|PdModuli|pd_tet_mesh_restart|implicit_scene_reports_cg|PdForms.HomogeneousDeformation|PdPlasticity.HydrostaticLoad|ParticleDomains.TwistCompress|ParticleDomains.StretchedBar|ParticleDomains.ImplicitMatches|interrupt_points_(mpm|mpm_fused|mpm_lazy_sort|implicit|aul|domains|pd)$|simd_paths_bitwise|BackendDeterminism.ImplicitBitwiseIdentical" "$@"
