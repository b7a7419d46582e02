// amalgam: command-line entry point (run, validate, bench, plot, surface, info).
#include <Eigen/Core>
#include <exception>
#include <memory>
#include <iostream>
#include <new>
#include <string>
#include <tbb/version.h>
#include <vector>

#include "apps/commands.hpp"
#include "core/dist/comm.hpp"
#include "core/exec/cpus.hpp"
#include "core/exec/exec.hpp"
#include "core/exec/simd.hpp"
#include "core/math/types.hpp"

namespace amalgam::cli {

int info_command(const std::vector<std::string>&) {
  std::cout << "amalgam " << AMALGAM_VERSION << "\n"
            << "precision: " << real_name() << "\n"
            << "backends: ";
  for (auto b : exec::available_backends()) std::cout << exec::backend_name(b) << " ";
  std::cout << "\nhardware threads: " << exec::hardware_threads() << " (this process may use "
            << exec::usable_threads() << ")\n"
            << "SIMD path: " << exec::simd_description() << "\n"
            << "Eigen " << EIGEN_WORLD_VERSION << "." << EIGEN_MAJOR_VERSION << "."
            << EIGEN_MINOR_VERSION << ", oneTBB " << TBB_VERSION_MAJOR << "." << TBB_VERSION_MINOR
            << ", OpenVDB " << AMALGAM_OPENVDB_VERSION << "\n";
  if (exec::backend_compiled(exec::Backend::Kokkos)) std::cout << exec::kokkos_version() << "\n";
  std::cout << "MPI: "
            << (dist::mpi_built()
                    ? "built in (MPI + Zoltan), " + std::to_string(dist::Comm::world().size()) +
                          " rank(s) in this run"
                    : std::string("not built (single process)"))
            << "\n";
  return kOk;
}

}  // namespace amalgam::cli

namespace {

int dispatch(int argc, char** argv) {
  using namespace amalgam::cli;
  const char* usage =
      "usage: amalgam <command> [options]\n"
      "commands:\n"
      "  run SCENE.json   simulate a scene, writing PLY frames and diagnostics (run --help)\n"
      "  validate SCENE   check a scene file without running it\n"
      "  bench            standard benchmark across backends and thread counts (bench --help)\n"
      "  plot RUN_DIR     draw a run's diagnostics.csv to diagnostics.png (plot --help)\n"
      "  surface RUN_DIR  surface a run's frames into level set, density and mesh files "
      "(surface --help)\n"
      "  merge RUN_DIR    join the per-rank parts of an MPI run (run --parts ranks) into the\n"
      "                   files one process writes (merge --help)\n"
      "  info             version, backends, precision, SIMD path, dependency versions\n"
      "every command takes --simd baseline|avx2|avx512|auto (default: $AMALGAM_SIMD, else auto,\n"
      "the widest vector path this CPU runs); results are bitwise the same on every path\n";
  if (argc < 2) {
    std::cerr << usage;
    return kUsage;
  }
  const std::string cmd = argv[1];
  // --simd PATH (or --simd=PATH), any command: the kernels' vector path (core/exec/simd.hpp).
  std::vector<std::string> args;
  std::string simd;
  bool simd_given = false;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--simd") {
      if (i + 1 >= argc) {
        std::cerr << "amalgam: --simd needs a value (baseline, avx2, avx512 or auto)\n";
        return kUsage;
      }
      simd = argv[++i], simd_given = true;
    } else if (a.rfind("--simd=", 0) == 0) {
      simd = a.substr(7), simd_given = true;
    } else {
      args.push_back(a);
    }
  }
  try {
    if (simd_given)
      amalgam::exec::set_simd_path(amalgam::exec::parse_simd_path(simd));
    else
      amalgam::exec::simd_path();  // an invalid AMALGAM_SIMD is refused here, before any work
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam: " << printable(e.what()) << "\n";
    return kUsage;
  }
  if (cmd == "run") return run_command(args);
  if (cmd == "validate") return validate_command(args);
  if (cmd == "bench") return bench_command(args);
  if (cmd == "info") return info_command(args);
  if (cmd == "plot") return plot_command(args);
  if (cmd == "surface") return surface_command(args);
  if (cmd == "merge") return merge_command(args);
  if (cmd == "--help" || cmd == "-h" || cmd == "help") {
    std::cout << usage;
    return kOk;
  }
  std::cerr << "amalgam: unknown command '" << printable(cmd) << "'\n" << usage;
  return kUsage;
}

}  // namespace

// The one top-level handler: every command maps the errors it expects to its exit code (README,
// "Exit codes"); anything else that escapes (out of memory, a library's own exception) ends here
// as exit 3 with what the process was doing, never as an abort.
int main(int argc, char** argv) {
  using namespace amalgam::cli;
  g_age_at_main = process_age_seconds();  // the set-up summary's "start" (amalgam run)
  std::unique_ptr<amalgam::dist::Session> mpi;
  int rc = kBadInput;
  try {
    mpi = std::make_unique<amalgam::dist::Session>(&argc, &argv);  // MPI_Init under mpirun
    rc = dispatch(argc, argv);
  } catch (const std::bad_alloc&) {
    std::cerr << "amalgam: error: out of memory while " << printable(current_phase())
              << " (the input asks for more than this machine has)\n";
  } catch (const std::exception& e) {
    std::cerr << "amalgam: error: while " << printable(current_phase()) << ": "
              << printable(e.what()) << "\n";
  } catch (...) {
    std::cerr << "amalgam: error: while " << printable(current_phase()) << ": unknown exception\n";
  }
  // On several MPI ranks a rank that stops with an error ends the whole job with its exit code:
  // the others may be waiting in a collective for it, and must not hang.
  const amalgam::dist::Comm& comm = amalgam::dist::Comm::world();
  if (rc != kOk && comm.size() > 1) {
    std::cerr << "amalgam: MPI rank " << comm.rank() << " of " << comm.size()
              << " stopped with exit code " << rc << "; ending every rank\n";
    std::cerr.flush();
    comm.abort(rc);
  }
  return rc;
}
