#include "io/writers.hpp"

#include <unistd.h>

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <stdexcept>

#include "core/errors.hpp"
#include "io/files.hpp"

namespace amalgam {

void write_file_atomic(const std::string& path, const std::string& content) {
  TempFile tmp(path);
  tmp.write(content.data(), content.size());
  tmp.commit();
}

namespace {
// The PLY property names of an attribute: its name, name_x/_y/_z (Vec3), or F00 .. F22 (Mat3:
// row, column).
std::vector<std::string> ply_properties(const PointAttribute& a) {
  using T = PointAttribute::Type;
  if (a.type == T::Vec3) return {a.name + "_x", a.name + "_y", a.name + "_z"};
  if (a.type != T::Mat3) return {a.name};
  std::vector<std::string> out;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) out.push_back(a.name + char('0' + r) + char('0' + c));
  return out;
}
}  // namespace

void write_ply_points(const std::string& path, const PointFields& p) {
  const size_t n = p.n;
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam\n"
    << "element vertex " << n << "\n"
    << "property float x\nproperty float y\nproperty float z\n"
    << "property float vx\nproperty float vy\nproperty float vz\nproperty int id\n";
  size_t record = 7 * 4;
  for (const PointAttribute& a : p.attributes) {
    const char* type = a.type == PointAttribute::Type::Int ? "int" : "float";
    for (const std::string& name : ply_properties(a))
      h << "property " << type << " " << name << "\n";
    record += 4 * size_t(a.width());
    if (a.name == "material")  // the names by index, as a JSON array (ASCII, escaped)
      h << "comment material_names " << nlohmann::json(p.material_names).dump(-1, ' ', true)
        << "\n";
  }
  h << "end_header\n";
  std::string buf = h.str();
  const size_t header = buf.size();
  buf.resize(header + n * record);
  char* dst = buf.data() + header;
  for (size_t i = 0; i < n; ++i) {
    const float rec[6] = {float(p.x[i][0]), float(p.x[i][1]), float(p.x[i][2]),
                          float(p.v[i][0]), float(p.v[i][1]), float(p.v[i][2])};
    std::memcpy(dst, rec, sizeof rec);
    std::memcpy(dst + sizeof rec, &p.id[i], 4);
    size_t off = sizeof rec + 4;
    for (const PointAttribute& a : p.attributes) {
      const size_t w = size_t(a.width());
      if (a.type == PointAttribute::Type::Int)
        std::memcpy(dst + off, &a.i[i], 4);
      else
        std::memcpy(dst + off, &a.f[w * i], 4 * w);
      off += 4 * w;
    }
    dst += record;
  }
  write_file_atomic(path, buf);
}

namespace {
void check_mesh(const std::string& path, const SurfaceMesh& m) {
  const std::size_t nv = m.vertices.size(), nt = m.triangles.size();
  if ((!m.normals.empty() && m.normals.size() != nv) ||
      (!m.velocity.empty() && m.velocity.size() != nv) ||
      (!m.crack.empty() && m.crack.size() != nt))
    throw std::logic_error(path + ": mesh arrays of different lengths");
}

template <class T>
void put(std::string& buf, const T& value) {
  char b[sizeof(T)];
  std::memcpy(b, &value, sizeof(T));
  buf.append(b, sizeof(T));  // the project's targets are little-endian, as the PLY header says
}
}  // namespace

void write_mesh_obj(const std::string& path, const SurfaceMesh& m, const std::string& what) {
  check_mesh(path, m);
  const bool normals = !m.normals.empty(), groups = !m.crack.empty();
  std::string out = "# written by Amalgam: " + what + "\n";
  out.reserve(out.size() + m.vertices.size() * (normals ? 80 : 40) + m.triangles.size() * 40);
  char line[160];
  for (const Vec3& v : m.vertices) {
    std::snprintf(line, sizeof line, "v %.7g %.7g %.7g\n", double(v[0]), double(v[1]),
                  double(v[2]));
    out += line;
  }
  for (const Vec3& n : m.normals) {
    std::snprintf(line, sizeof line, "vn %.5g %.5g %.5g\n", double(n[0]), double(n[1]),
                  double(n[2]));
    out += line;
  }
  for (int group = 0; group < (groups ? 2 : 1); ++group) {
    if (groups) out += group == 0 ? "g surface\n" : "g crack\n";
    for (std::size_t f = 0; f < m.triangles.size(); ++f) {
      if (groups && int(m.crack[f] != 0) != group) continue;
      const auto& t = m.triangles[f];
      if (normals)
        std::snprintf(line, sizeof line, "f %u//%u %u//%u %u//%u\n", t[0] + 1, t[0] + 1, t[1] + 1,
                      t[1] + 1, t[2] + 1, t[2] + 1);
      else
        std::snprintf(line, sizeof line, "f %u %u %u\n", t[0] + 1, t[1] + 1, t[2] + 1);
      out += line;
    }
  }
  write_file_atomic(path, out);
}

void write_mesh_ply(const std::string& path, const SurfaceMesh& m, const std::string& what) {
  check_mesh(path, m);
  const bool normals = !m.normals.empty(), velocity = !m.velocity.empty(), crack = !m.crack.empty();
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam: " << what << "\n"
    << "element vertex " << m.vertices.size() << "\n"
    << "property float x\nproperty float y\nproperty float z\n";
  if (normals) h << "property float nx\nproperty float ny\nproperty float nz\n";
  if (velocity) h << "property float vx\nproperty float vy\nproperty float vz\n";
  h << "element face " << m.triangles.size() << "\n"
    << "property list uchar uint vertex_indices\n";
  if (crack) h << "property uchar crack\n";
  h << "end_header\n";
  std::string buf = h.str();
  buf.reserve(buf.size() + m.vertices.size() * 36 + m.triangles.size() * 14);
  for (std::size_t i = 0; i < m.vertices.size(); ++i) {
    for (int k = 0; k < 3; ++k) put(buf, float(m.vertices[i][k]));
    if (normals)
      for (int k = 0; k < 3; ++k) put(buf, float(m.normals[i][k]));
    if (velocity)
      for (int k = 0; k < 3; ++k) put(buf, float(m.velocity[i][k]));
  }
  for (std::size_t f = 0; f < m.triangles.size(); ++f) {
    put(buf, std::uint8_t(3));
    for (int k = 0; k < 3; ++k) put(buf, std::uint32_t(m.triangles[f][k]));
    if (crack) put(buf, std::uint8_t(m.crack[f]));
  }
  write_file_atomic(path, buf);
}

std::string csv_header(const std::vector<Column>& columns) {
  std::string out;
  for (const Column& c : columns) out += (out.empty() ? "" : ",") + c.name;
  return out + "\n";
}

std::string csv_row(const std::vector<Column>& columns) {
  std::ostringstream os;
  os.precision(9);
  for (std::size_t k = 0; k < columns.size(); ++k) {
    if (k) os << ',';
    if (columns[k].integer)
      os << (long long)columns[k].value;
    else
      os << columns[k].value;
  }
  os << '\n';
  return os.str();
}

double resident_mb() {
  std::ifstream in("/proc/self/statm");
  long long pages_total = 0, pages_resident = 0;
  if (!(in >> pages_total >> pages_resident)) return 0;
  return double(pages_resident) * double(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

}  // namespace amalgam
