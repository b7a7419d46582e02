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

PointFields mpm_point_fields(const ParticleSet& ps, const MpmAttributes& a) {
  PointFields p;
  p.n = ps.size();
  p.x = ps.vec3(a.x);
  p.v = ps.vec3(a.v);
  p.material = ps.int32(a.material);
  p.id = ps.int32(a.id);
  std::vector<float> J(p.n);
  const Mat3* F = ps.mat3(a.F);
  for (std::size_t i = 0; i < p.n; ++i) J[i] = float(F[i].determinant());
  p.primary.emplace_back("J", std::move(J));
  // Method-specific state, when the scene's materials carry it.
  for (const auto& [attr, name] : {std::pair<ParticleSet::Id, const char*>{a.plastic, "plastic"},
                                   std::pair<ParticleSet::Id, const char*>{a.temperature, "temperature"}}) {
    if (attr < 0) continue;
    const Real* r = ps.real(attr);
    p.extra.emplace_back(name, std::vector<float>(r, r + p.n));
  }
  // Enriched MPM: the particle's enrichment state (-1 domain disabled, 0 unenriched,
  // 1 transitional, 2 enriched; enriched MPM Fig. 3), for colour-mapping as in Figs. 6 and 10.
  const ParticleSet::Id ds = ps.find("domain_state");
  if (ds >= 0) {
    const std::int32_t* st = ps.int32(ds);
    std::vector<float> e(p.n);
    for (std::size_t i = 0; i < p.n; ++i) e[i] = float(st[i]);
    p.extra.emplace_back("enrichment", std::move(e));
  }
  return p;
}

void write_ply_points(const std::string& path, const PointFields& p) {
  const size_t n = p.n;
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam\n"
    << "element vertex " << n << "\n"
    << "property float x\nproperty float y\nproperty float z\n"
    << "property float vx\nproperty float vy\nproperty float vz\n";
  for (const auto& s : p.primary) h << "property float " << s.first << "\n";
  h << "property int material\nproperty int id\n";
  for (const auto& s : p.extra) h << "property float " << s.first << "\n";
  h << "end_header\n";
  std::string buf = h.str();
  const size_t header = buf.size();
  const size_t kRecord = 6 * 4 + 4 * p.primary.size() + 8 + 4 * p.extra.size();
  buf.resize(header + n * kRecord);
  char* dst = buf.data() + header;
  for (size_t i = 0; i < n; ++i) {
    const float rec[6] = {float(p.x[i][0]), float(p.x[i][1]), float(p.x[i][2]),
                          float(p.v[i][0]), float(p.v[i][1]), float(p.v[i][2])};
    std::memcpy(dst, rec, sizeof rec);
    size_t off = sizeof rec;
    for (const auto& s : p.primary) std::memcpy(dst + off, &s.second[i], 4), off += 4;
    std::memcpy(dst + off, &p.material[i], 4);
    std::memcpy(dst + off + 4, &p.id[i], 4);
    off += 8;
    for (const auto& s : p.extra) std::memcpy(dst + off, &s.second[i], 4), off += 4;
    dst += kRecord;
  }
  write_file_atomic(path, buf);
}

void write_surface_obj(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles, const std::vector<std::uint8_t>& crack) {
  std::string out = "# written by Amalgam: deformed surface (group crack: peridynamic crack faces)\n";
  out.reserve(out.size() + vertices.size() * 40 + triangles.size() * 30);
  char line[96];
  for (const Vec3& v : vertices) {
    std::snprintf(line, sizeof line, "v %.7g %.7g %.7g\n", double(v[0]), double(v[1]), double(v[2]));
    out += line;
  }
  for (int group = 0; group < 2; ++group) {
    out += group == 0 ? "g surface\n" : "g crack\n";
    for (std::size_t f = 0; f < triangles.size(); ++f) {
      if (int(crack[f] != 0) != group) continue;
      std::snprintf(line, sizeof line, "f %u %u %u\n", triangles[f][0] + 1, triangles[f][1] + 1, triangles[f][2] + 1);
      out += line;
    }
  }
  write_file_atomic(path, out);
}

void write_surface_ply(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles, const std::vector<std::uint8_t>& crack) {
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam: surface with crack faces\n"
    << "element vertex " << vertices.size() << "\nproperty float x\nproperty float y\nproperty float z\n"
    << "element face " << triangles.size() << "\nproperty list uchar int vertex_indices\nproperty uchar crack\n"
    << "end_header\n";
  std::string buf = h.str();
  const std::size_t header = buf.size();
  buf.resize(header + vertices.size() * 12 + triangles.size() * 14);
  char* dst = buf.data() + header;
  for (const Vec3& v : vertices) {
    const float p[3] = {float(v[0]), float(v[1]), float(v[2])};
    std::memcpy(dst, p, 12);
    dst += 12;
  }
  for (std::size_t f = 0; f < triangles.size(); ++f) {
    *dst++ = 3;
    const std::int32_t idx[3] = {std::int32_t(triangles[f][0]), std::int32_t(triangles[f][1]), std::int32_t(triangles[f][2])};
    std::memcpy(dst, idx, 12);
    dst += 12;
    *dst++ = char(crack[f]);
  }
  write_file_atomic(path, buf);
}

std::string diagnostics_csv_header() {
  return "frame,time_s,last_dt_s,substeps,kinetic_J,elastic_J,momentum_x,momentum_y,momentum_z,max_speed_m_s,"
         "particles,wall_s,p2g_s,g2p_s,sort_s,grid_s,other_s,leaves,active_leaves,rss_mb,solve_s,cg_iterations,"
         "cg_max_iterations,cg_max_residual,cg_unconverged,enriched_fraction,transitional_fraction,"
         "max_enriched_fraction,enriched_corners\n";
}

std::string diagnostics_csv_line(const DiagnosticsRow& r) {
  std::ostringstream os;
  os.precision(9);
  os << r.frame << ',' << r.time << ',' << r.dt << ',' << r.substeps << ',' << r.d.kinetic << ',' << r.d.elastic << ','
     << r.d.momentum[0] << ',' << r.d.momentum[1] << ',' << r.d.momentum[2] << ',' << r.d.max_speed << ','
     << r.particles << ',' << r.wall_seconds << ',' << r.p2g_s << ',' << r.g2p_s << ',' << r.sort_s << ','
     << r.grid_s << ',' << r.other_s << ',' << r.leaves << ',' << r.active_leaves << ',' << r.rss_mb << ','
     << r.solve_s << ',' << r.cg_iterations << ',' << r.cg_max_iterations << ',' << r.cg_max_residual << ','
     << r.cg_unconverged << ',' << r.enriched_fraction << ',' << r.transitional_fraction << ','
     << r.max_enriched_fraction << ',' << r.enriched_corners << '\n';
  return os.str();
}

double resident_mb() {
  std::ifstream in("/proc/self/statm");
  long long pages_total = 0, pages_resident = 0;
  if (!(in >> pages_total >> pages_resident)) return 0;
  return double(pages_resident) * double(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

}  // namespace amalgam
