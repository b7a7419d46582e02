// `amalgam surface RUN_DIR`: surfaces the frames a run wrote (frame_NNNN.vdb points) into
// surfacing_NNNN.vdb (+ .obj / .ply), as output.surfacing does during a run (io/surfacing.hpp).
// Parallel over frames and within a frame: K frames at a time (--frames-at-once, default
// --threads) through the exec layer, each frame's OpenVDB tools on --threads / K threads; memory:
// K frames' particles and grids.
#include <algorithm>
#include <chrono>
#include <exception>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "apps/commands.hpp"
#include "core/errors.hpp"
#include "core/exec/cpus.hpp"
#include "io/scene.hpp"
#include "io/surfacing.hpp"

namespace amalgam::cli {

namespace {

const char* kSurfaceHelp =
    "usage: amalgam surface RUN_DIR [--scene SCENE.json] [--method smooth|spheres]\n"
    "                       [--voxel-size M] [--radius-scale S] [--spacing M]\n"
    "                       [--filters dilate,smooth,erode|none] [--grids surface,density,v]\n"
    "                       [--mesh none|obj|ply] [--adaptivity A] [--groups MATERIAL,...]\n"
    "                       [--frames A-B] [--threads N] [--frames-at-once K] [--out DIR]\n"
    "                       [--quiet]\n"
    "Surfaces the frames RUN_DIR/frame_NNNN.vdb (VDB points written by amalgam run) into\n"
    "DIR/surfacing_NNNN.vdb with the grids surface (level set), density (fog volume) and v\n"
    "(velocity), and with --mesh a triangle mesh surfacing_NNNN.obj or .ply (docs/scenes.md,\n"
    "output.surfacing). K frames at a time (default K = --threads), each frame's OpenVDB tools\n"
    "on --threads / K threads: at most K frames in memory; the files are the same bytes for any\n"
    "--threads and K.\n"
    "--scene takes the defaults from the scene the run used: its output.surfacing block, the\n"
    "voxel size dx / 2, the particle spacing and the material names for --groups; options given\n"
    "here override it. Without --scene the voxel size and the particle spacing default to half\n"
    "the points' voxel (the run's dx for MPM: right for 8 particles per cell; give --spacing\n"
    "otherwise).\n"
    "Defaults: --out = RUN_DIR, every frame, --threads = the CPUs this process may run on.\n";

std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream in(s);
  std::string item;
  while (std::getline(in, item, ','))
    if (!item.empty()) out.push_back(item);
  return out;
}

// The options given on the command line, over the scene's (or the default) spec.
void apply_options(const Options& o, const Scene* scene, SurfacingSpec& s) {
  if (const auto* v = o.get("--method")) {
    if (!parse_surfacing_method(*v, s.method))
      throw std::invalid_argument("--method: expected smooth or spheres, got '" + *v + "'");
    if (!o.get("--filters")) s.filters = default_surface_filters(s.method);
  }
  if (const auto* v = o.get("--voxel-size"))
    s.voxel_size = parse_double("--voxel-size", *v, 0, 1e30);
  if (!(s.voxel_size > 0) && o.get("--voxel-size"))
    throw std::invalid_argument("--voxel-size: expected a positive number");
  if (const auto* v = o.get("--radius-scale"))
    s.radius_scale = parse_double("--radius-scale", *v, 1e-6, 100);
  if (const auto* v = o.get("--filters")) {
    s.filters.clear();
    for (const std::string& f : split_list(*v == "none" ? "" : *v)) {
      SurfaceFilter k;
      if (!parse_surface_filter(f, k))
        throw std::invalid_argument("--filters: unknown filter '" + f +
                                    "' (expected dilate, smooth, erode or none)");
      s.filters.push_back(k);
    }
  }
  if (const auto* v = o.get("--grids")) {
    s.grid_surface = s.grid_density = s.grid_velocity = false;
    for (const std::string& g : split_list(*v)) {
      bool* flag = g == "surface"   ? &s.grid_surface
                   : g == "density" ? &s.grid_density
                   : g == "v"       ? &s.grid_velocity
                                    : nullptr;
      if (!flag)
        throw std::invalid_argument("--grids: unknown grid '" + g +
                                    "' (expected surface, density, v)");
      *flag = true;
    }
  }
  if (const auto* v = o.get("--mesh"))
    if (!parse_surface_mesh(*v, s.mesh))
      throw std::invalid_argument("--mesh: expected none, obj or ply, got '" + *v + "'");
  if (const auto* v = o.get("--adaptivity")) s.adaptivity = parse_double("--adaptivity", *v, 0, 1);
  if (const auto* v = o.get("--groups")) {
    if (!scene) throw std::invalid_argument("--groups names materials: give --scene too");
    s.materials.clear();
    for (const std::string& g : split_list(*v)) {
      const auto& names = scene->material_names;
      std::size_t k = 0;
      while (k < names.size() && names[k] != g) ++k;
      if (k == names.size())
        throw InputError(scene->file + ": --groups: unknown material \"" + g + "\"");
      s.materials.push_back(std::int32_t(k));
    }
  }
}

// frame_NNNN.vdb files of the run directory, by frame number, within [first, last].
std::map<int, std::string> frames_in(const std::string& dir, int first, int last) {
  std::map<int, std::string> frames;
  std::error_code ec;
  std::filesystem::directory_iterator it(dir, ec);
  if (ec) throw InputError(dir + ": cannot read run directory: " + ec.message());
  for (const auto& e : it) {
    const std::string name = e.path().filename().string();
    int f = -1, used = 0;
    if (name.size() == 14 && std::sscanf(name.c_str(), "frame_%4d.vdb%n", &f, &used) == 1 &&
        used == 14 && f >= first && f <= last)
      frames[f] = e.path().string();
  }
  return frames;
}

}  // namespace

int surface_command(const std::vector<std::string>& args) {
  Options o;
  int first = 0, last = 9999;
  int threads = exec::usable_threads();
  int frames_at_once = 0;  // 0: as many as threads
  try {
    o = parse_options(args,
                      {"--scene", "--method", "--voxel-size", "--radius-scale", "--spacing",
                       "--filters", "--grids", "--mesh", "--adaptivity", "--groups", "--frames",
                       "--frames-at-once", "--threads", "--out"},
                      {"--help", "--quiet"});
    if (o.flag("--help")) {
      std::cout << kSurfaceHelp;
      return kOk;
    }
    if (o.positional.size() != 1) throw std::invalid_argument("expected exactly one run directory");
    if (const auto* f = o.get("--frames")) {
      const std::size_t dash = f->find('-');
      if (dash == std::string::npos) {
        first = last = parse_int("--frames", *f, 0, 9999);
      } else {
        first = parse_int("--frames", f->substr(0, dash), 0, 9999);
        last = parse_int("--frames", f->substr(dash + 1), 0, 9999);
        if (last < first) throw std::invalid_argument("--frames: expected A-B with A <= B");
      }
    }
    if (const auto* t = o.get("--threads")) threads = parse_int("--threads", *t, 1, 4096);
    if (const auto* c = o.get("--frames-at-once"))
      frames_at_once = parse_int("--frames-at-once", *c, 1, 4096);
    if (frames_at_once == 0) frames_at_once = threads;
  } catch (const std::invalid_argument& e) {
    std::cerr << "amalgam surface: " << printable(e.what()) << "\n" << kSurfaceHelp;
    return kUsage;
  }
  try {
    const std::string dir = o.positional[0];
    const std::string out = o.get("--out") ? *o.get("--out") : dir;
    SurfacingSpec spec;
    double spacing = 0;  // 0: from the points (surface_vdb_points_file)
    std::unique_ptr<Scene> scene;
    if (const auto* path = o.get("--scene")) {
      set_phase("reading scene file " + *path);
      scene = std::make_unique<Scene>(load_scene(*path));
      if (scene->output.surfacing.enabled) spec = scene->output.surfacing;
      if (!(spec.voxel_size > 0)) spec.voxel_size = 0.5 * double(scene->mpm.dx);
      spacing = particle_spacing(*scene);
    }
    try {
      apply_options(o, scene.get(), spec);
      if (const auto* v = o.get("--spacing")) spacing = parse_double("--spacing", *v, 1e-9, 1e30);
    } catch (const std::invalid_argument& e) {
      std::cerr << "amalgam surface: " << printable(e.what()) << "\n" << kSurfaceHelp;
      return kUsage;
    }
    const std::map<int, std::string> frames = frames_in(dir, first, last);
    if (frames.empty())
      throw InputError(dir + ": no frame_NNNN.vdb files" +
                       (o.get("--frames") ? " in --frames " + *o.get("--frames") : std::string()) +
                       " (the run needs output.vdb_points)");
    std::error_code ec;
    std::filesystem::create_directories(out, ec);
    if (ec) throw InputError(out + ": cannot create output directory: " + ec.message());
    // Frames in waves of `concurrent`, each frame's OpenVDB tools on its share of the threads
    // (exec::with_thread_limit inside write_surfacing): at most `concurrent` frames' particles
    // and grids in memory; every frame's files depend only on its input, so the output is the
    // same bytes whatever the thread count. Progress is printed per frame, in frame order, as
    // each wave ends.
    const int concurrent = std::max(1, std::min({frames_at_once, threads, int(frames.size())}));
    const exec::Space outer(exec::Backend::TBB, concurrent);
    const exec::Space inner(exec::Backend::TBB, std::max(1, threads / concurrent));
    const std::vector<std::pair<int, std::string>> list(frames.begin(), frames.end());
    const auto t0 = std::chrono::steady_clock::now();
    std::size_t done = 0, particles = 0;
    for (std::size_t w = 0; w < list.size(); w += std::size_t(concurrent)) {
      const std::size_t n = std::min(list.size() - w, std::size_t(concurrent));
      set_phase("surfacing " + list[w].second + (n > 1 ? " to " + list[w + n - 1].second : ""));
      std::vector<SurfacingStats> stats(n);
      std::vector<std::exception_ptr> errors(n);  // rethrown in frame order after the wave
      std::vector<double> seconds(n, 0.0);
      exec::parallel_for_chunks(
          outer, "surface_frames", exec::Index(n), 1, [&](exec::Index b, exec::Index e) {
            for (exec::Index k = b; k < e; ++k) {
              const auto& [f, path] = list[w + std::size_t(k)];
              char base[32];
              std::snprintf(base, sizeof base, "/surfacing_%04d", f);
              const auto t = std::chrono::steady_clock::now();
              try {
                stats[k] = surface_vdb_points_file(path, out + base, spacing, spec, inner);
              } catch (...) {
                errors[k] = std::current_exception();
              }
              seconds[k] =
                  std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
            }
          });
      for (std::size_t k = 0; k < n; ++k) {
        if (errors[k]) std::rethrow_exception(errors[k]);
        ++done;
        particles += stats[k].particles;
        if (!o.flag("--quiet")) {
          std::printf("frame %d (%zu/%zu): %zu particles, %zu voxels, %zu triangles, %.2f s\n",
                      list[w + k].first, done, list.size(), stats[k].particles,
                      stats[k].active_voxels, stats[k].triangles, seconds[k]);
          std::fflush(stdout);
        }
      }
    }
    if (!o.flag("--quiet")) {
      const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      std::printf("amalgam: surfaced %zu frames (%zu particles) in %.2f s on %d threads into %s/\n",
                  done, particles, s, threads, out.c_str());
    }
    return kOk;
  } catch (const InputError& e) {
    std::cerr << "amalgam: error: " << printable(e.what()) << "\n";
    return kBadInput;
  }
}

}  // namespace amalgam::cli
