#include "io/writers.hpp"

#include <unistd.h>

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

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

void write_surface_obj(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles,
                       const std::vector<std::uint8_t>& crack) {
  std::string out =
      "# written by Amalgam: deformed surface (group crack: peridynamic crack faces)\n";
  out.reserve(out.size() + vertices.size() * 40 + triangles.size() * 30);
  char line[96];
  for (const Vec3& v : vertices) {
    std::snprintf(line, sizeof line, "v %.7g %.7g %.7g\n", double(v[0]), double(v[1]),
                  double(v[2]));
    out += line;
  }
  for (int group = 0; group < 2; ++group) {
    out += group == 0 ? "g surface\n" : "g crack\n";
    for (std::size_t f = 0; f < triangles.size(); ++f) {
      if (int(crack[f] != 0) != group) continue;
      std::snprintf(line, sizeof line, "f %u %u %u\n", triangles[f][0] + 1, triangles[f][1] + 1,
                    triangles[f][2] + 1);
      out += line;
    }
  }
  write_file_atomic(path, out);
}

void write_surface_ply(const std::string& path, const std::vector<Vec3>& vertices,
                       const std::vector<std::array<std::uint32_t, 3>>& triangles,
                       const std::vector<std::uint8_t>& crack) {
  std::ostringstream h;
  h << "ply\nformat binary_little_endian 1.0\ncomment written by Amalgam: surface with crack faces\n"
    << "element vertex " << vertices.size()
    << "\nproperty float x\nproperty float y\nproperty float z\n"
    << "element face " << triangles.size()
    << "\nproperty list uchar int vertex_indices\nproperty uchar crack\n"
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
    const std::int32_t idx[3] = {std::int32_t(triangles[f][0]), std::int32_t(triangles[f][1]),
                                 std::int32_t(triangles[f][2])};
    std::memcpy(dst, idx, 12);
    dst += 12;
    *dst++ = char(crack[f]);
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
