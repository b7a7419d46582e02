#include "io/writers.hpp"

#include <unistd.h>

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "core/errors.hpp"

namespace amalgam {

void write_file_atomic(const std::string& path, const std::string& content) {
  const std::string tmp = path + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    if (!out) throw InputError(path + ": cannot open for writing");
    out.write(content.data(), std::streamsize(content.size()));
    out.flush();
    if (!out) {
      std::remove(tmp.c_str());
      throw InputError(path + ": write failed (disk full?)");
    }
  }
  commit_temporary(tmp, path);
}

void commit_temporary(const std::string& tmp, const std::string& path) {
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::remove(tmp.c_str());
    throw InputError(path + ": cannot rename temporary file: " + ec.message());
  }
}

void write_ply_points(const std::string& path, const ParticleSet& ps, const MpmAttributes& a) {
  const size_t n = ps.size();
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam\n"
    << "element vertex " << n << "\n"
    << "property float x\nproperty float y\nproperty float z\n"
    << "property float vx\nproperty float vy\nproperty float vz\n"
    << "property float J\nproperty int material\nproperty int id\n";
  // Method-specific state, when the scene's materials carry it.
  const Real* extra[2] = {a.plastic >= 0 ? ps.real(a.plastic) : nullptr,
                          a.temperature >= 0 ? ps.real(a.temperature) : nullptr};
  if (extra[0]) h << "property float plastic\n";
  if (extra[1]) h << "property float temperature\n";
  h << "end_header\n";
  std::string buf = h.str();
  const size_t header = buf.size();
  const size_t kRecord = 7 * 4 + 4 + 4 + 4 * size_t((extra[0] != nullptr) + (extra[1] != nullptr));
  buf.resize(header + n * kRecord);
  const Vec3* x = ps.vec3(a.x);
  const Vec3* v = ps.vec3(a.v);
  const Mat3* F = ps.mat3(a.F);
  const std::int32_t* mat = ps.int32(a.material);
  const std::int32_t* id = ps.int32(a.id);
  char* dst = buf.data() + header;
  for (size_t i = 0; i < n; ++i) {
    const float rec[7] = {float(x[i][0]), float(x[i][1]), float(x[i][2]), float(v[i][0]),
                          float(v[i][1]), float(v[i][2]), float(F[i].determinant())};
    std::memcpy(dst, rec, sizeof rec);
    std::memcpy(dst + sizeof rec, &mat[i], 4);
    std::memcpy(dst + sizeof rec + 4, &id[i], 4);
    size_t off = sizeof rec + 8;
    for (const Real* e : extra)
      if (e) {
        const float f = float(e[i]);
        std::memcpy(dst + off, &f, 4);
        off += 4;
      }
    dst += kRecord;
  }
  write_file_atomic(path, buf);
}

std::string diagnostics_csv_header() {
  return "frame,time_s,last_dt_s,substeps,kinetic_J,elastic_J,momentum_x,momentum_y,momentum_z,max_speed_m_s,"
         "particles,wall_s,p2g_s,g2p_s,sort_s,grid_s,other_s,leaves,active_leaves,rss_mb,solve_s,cg_iterations,"
         "cg_max_iterations,cg_max_residual,cg_unconverged\n";
}

std::string diagnostics_csv_line(const DiagnosticsRow& r) {
  std::ostringstream os;
  os.precision(9);
  os << r.frame << ',' << r.time << ',' << r.dt << ',' << r.substeps << ',' << r.d.kinetic << ',' << r.d.elastic << ','
     << r.d.momentum[0] << ',' << r.d.momentum[1] << ',' << r.d.momentum[2] << ',' << r.d.max_speed << ','
     << r.particles << ',' << r.wall_seconds << ',' << r.p2g_s << ',' << r.g2p_s << ',' << r.sort_s << ','
     << r.grid_s << ',' << r.other_s << ',' << r.leaves << ',' << r.active_leaves << ',' << r.rss_mb << ','
     << r.solve_s << ',' << r.cg_iterations << ',' << r.cg_max_iterations << ',' << r.cg_max_residual << ','
     << r.cg_unconverged << '\n';
  return os.str();
}

double resident_mb() {
  std::ifstream in("/proc/self/statm");
  long long pages_total = 0, pages_resident = 0;
  if (!(in >> pages_total >> pages_resident)) return 0;
  return double(pages_resident) * double(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

}  // namespace amalgam
