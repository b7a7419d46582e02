// `amalgam plot RUN_DIR`: draws RUN_DIR/diagnostics.csv to RUN_DIR/diagnostics.png.
#include <fstream>
#include <iostream>
#include <sstream>
#include <stdexcept>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "io/files.hpp"
#include "io/plot.hpp"

namespace amalgam::cli {

namespace {
const char* kPlotHelp =
    "usage: amalgam plot RUN_DIR [--out FILE.png] [--quiet]\n"
    "Draws RUN_DIR/diagnostics.csv (written by amalgam run) to a PNG with three panels: kinetic,\n"
    "elastic and total energy vs time; the substep dt vs time (log scale); seconds per frame in\n"
    "P2G, G2P, sort, grid and other. Default output: RUN_DIR/diagnostics.png.\n";
}  // namespace

int plot_command(const std::vector<std::string>& args) {
  Options o;
  try {
    o = parse_options(args, {"--out"}, {"--help", "--quiet"});
    if (o.flag("--help")) {
      std::cout << kPlotHelp;
      return kOk;
    }
    if (o.positional.size() != 1) throw std::invalid_argument("expected exactly one run directory");
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam plot: " << printable(e.what()) << "\n" << kPlotHelp;
    return kUsage;
  }
  try {
    const std::string dir = o.positional[0];
    const std::string csv = dir + "/diagnostics.csv";
    std::string text;
    try {
      text = read_input_file(csv, "diagnostics file", std::uint64_t(1) << 30);
    } catch (const InputError& e) {
      throw InputError(std::string(e.what()) + " (run the scene with output.diagnostics_csv)");
    }
    const auto cols = read_csv_columns(text, csv);
    const std::string out = o.get("--out") ? *o.get("--out") : dir + "/diagnostics.png";
    write_png(out, plot_diagnostics(cols, "AMALGAM DIAGNOSTICS: " + dir));
    if (!o.flag("--quiet")) std::cout << "amalgam: wrote " << out << "\n";
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << printable(e.what()) << "\n";
    return kBadInput;
  }
}

}  // namespace amalgam::cli
