// `amalgam merge RUN_DIR`: joins the per-rank parts of a distributed run (`run --parts ranks`,
// io/parts.hpp, io/checkpoint.hpp) into the files one process writes, bitwise.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <stdexcept>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "core/exec/cpus.hpp"
#include "io/checkpoint.hpp"
#include "io/files.hpp"
#include "io/parts.hpp"

namespace amalgam::cli {

namespace {
const char* kMergeHelp =
    "usage: amalgam merge RUN_DIR [--threads N] [--remove-parts]\n"
    "Joins the per-rank parts of a run made with `amalgam run --parts ranks` (MPI): for every\n"
    "frame with a manifest (frame_NNNN.manifest.json; a frame without one is incomplete and is\n"
    "skipped) its parts frame_NNNN.rRRR.pts become frame_NNNN.ply / .vdb, and a per-rank\n"
    "checkpoint (checkpoint.amck naming checkpoint.gGGGGGG.rRRR.amck parts) becomes one file:\n"
    "bitwise the files a single-process run writes. Every part is checked against its manifest\n"
    "(size, FNV-1a checksum) first; an error names the file and the rank (exit 3).\n"
    "--remove-parts removes the joined frames' parts and manifests and the checkpoint's parts.\n";
}  // namespace

int merge_command(const std::vector<std::string>& args) {
  Options o;
  try {
    o = parse_options(args, {"--threads"}, {"--help", "--remove-parts"});
    if (o.flag("--help")) {
      std::cout << kMergeHelp;
      return kOk;
    }
    if (o.positional.size() != 1) throw std::invalid_argument("expected exactly one run directory");
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam merge: " << printable(e.what()) << "\n" << kMergeHelp;
    return kUsage;
  }
  try {
    const std::string dir = o.positional[0];
    int threads = exec::usable_threads();
    if (const auto* t = o.get("--threads")) threads = parse_int("--threads", *t, 1, 4096);
    const exec::Space space(exec::Backend::OpenMP, threads);
    set_phase("merging the parts in " + dir);
    if (!std::filesystem::is_directory(dir))
      throw InputError(dir + ": not a directory (expected a run's output directory)");
    // Complete frames (with a manifest) and incomplete ones (parts, no manifest).
    std::vector<int> complete, incomplete;
    for (const auto& e : std::filesystem::directory_iterator(dir)) {
      const std::string name = e.path().filename().string();
      int f = 0, r = 0;
      char tail[32] = {0};
      if (std::sscanf(name.c_str(), "frame_%d.manifest.jso%1s", &f, tail) == 2 &&
          name == frame_manifest_name(f))
        complete.push_back(f);
      else if (std::sscanf(name.c_str(), "frame_%d.r%d.pts", &f, &r) == 2)
        incomplete.push_back(f);
    }
    std::sort(complete.begin(), complete.end());
    std::sort(incomplete.begin(), incomplete.end());
    incomplete.erase(std::unique(incomplete.begin(), incomplete.end()), incomplete.end());
    int merged = 0;
    for (int f : complete) {
      const FrameManifest m = read_frame_manifest(dir + "/" + frame_manifest_name(f));
      if (m.frame != f)
        throw InputError(dir + "/" + frame_manifest_name(f) + ": /frame: " +
                         std::to_string(m.frame) + ", expected " + std::to_string(f));
      merge_frame(dir, m, space);
      ++merged;
      if (o.flag("--remove-parts")) {
        for (const auto& rank : m.files)
          for (const PartFile& pf : rank) std::filesystem::remove(dir + "/" + pf.file);
        std::filesystem::remove(dir + "/" + frame_manifest_name(f));
      }
    }
    for (int f : incomplete)
      if (!std::binary_search(complete.begin(), complete.end(), f))
        std::cerr << "amalgam merge: frame " << f
                  << " has parts but no manifest (incomplete: the run stopped while writing "
                     "it); skipped\n";
    std::string checkpoint = "no per-rank checkpoint";
    const std::string ck = dir + "/checkpoint.amck";
    if (std::filesystem::exists(ck) && is_checkpoint_manifest(ck)) {
      write_file_atomic(ck, join_checkpoint(ck));
      if (o.flag("--remove-parts")) remove_stale_checkpoint_parts(dir, 0);
      checkpoint = "checkpoint.amck joined into one file";
    }
    std::cout << "amalgam merge: " << merged << " frame(s) joined in " << printable(dir) << "; "
              << checkpoint << "\n";
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << printable(e.what()) << "\n";
    return kBadInput;
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam merge: " << printable(e.what()) << "\n";
    return kUsage;
  }
}

}  // namespace amalgam::cli
