// Mesh file readers: OBJ, OFF and PLY (ASCII or binary little-endian).
#include "io/mesh.hpp"

#include <algorithm>
#include <cstring>
#include <fstream>
#include <sstream>

#include "core/errors.hpp"

namespace amalgam {

namespace {

std::string lower_ext(const std::string& path) {
  const auto dot = path.find_last_of('.');
  std::string e = dot == std::string::npos ? "" : path.substr(dot + 1);
  std::transform(e.begin(), e.end(), e.begin(),
                 [](unsigned char c) { return char(std::tolower(c)); });
  return e;
}

void add_polygon(TriangleMesh& m, const std::vector<std::int32_t>& poly, const std::string& where) {
  if (poly.size() < 3) throw InputError(where + ": a face needs at least 3 vertices");
  for (auto i : poly)
    if (i < 0 || size_t(i) >= m.vertices.size())
      throw InputError(where + ": vertex index " + std::to_string(i) + " out of range (" +
                       std::to_string(m.vertices.size()) + " vertices)");
  for (size_t k = 1; k + 1 < poly.size(); ++k)
    m.triangles.push_back({poly[0], poly[k], poly[k + 1]});
}

TriangleMesh read_obj(const std::string& path, std::istream& in) {
  TriangleMesh m;
  std::string line;
  int ln = 0;
  while (std::getline(in, line)) {
    ++ln;
    std::istringstream ss(line);
    std::string tag;
    ss >> tag;
    const std::string where = path + ":" + std::to_string(ln);
    if (tag == "v") {
      Vec3d p;
      if (!(ss >> p[0] >> p[1] >> p[2])) throw InputError(where + ": expected 'v x y z'");
      m.vertices.push_back(p);
    } else if (tag == "f") {
      std::vector<std::int32_t> poly;
      std::string tok;
      while (ss >> tok) {
        const long idx = std::strtol(tok.c_str(), nullptr, 10);  // "i", "i/t", "i//n", "i/t/n"
        if (idx == 0) throw InputError(where + ": bad face index '" + tok + "'");
        poly.push_back(std::int32_t(idx > 0 ? idx - 1 : long(m.vertices.size()) + idx));
      }
      add_polygon(m, poly, where);
    }
  }
  return m;
}

TriangleMesh read_off(const std::string& path, std::istream& in) {
  auto next_line = [&](std::string& line, int& ln) {
    while (std::getline(in, line)) {
      ++ln;
      const auto h = line.find('#');
      if (h != std::string::npos) line.resize(h);
      if (line.find_first_not_of(" \t\r") != std::string::npos) return true;
    }
    return false;
  };
  std::string line;
  int ln = 0;
  if (!next_line(line, ln) || line.rfind("OFF", 0) != 0)
    throw InputError(path + ":1: expected the 'OFF' header");
  std::istringstream rest(line.substr(3));
  long nv = -1, nf = -1;
  if (!(rest >> nv >> nf)) {
    if (!next_line(line, ln)) throw InputError(path + ": missing vertex/face counts");
    std::istringstream c(line);
    if (!(c >> nv >> nf))
      throw InputError(path + ":" + std::to_string(ln) + ": expected 'vertices faces edges'");
  }
  if (nv < 3 || nf < 1) throw InputError(path + ": needs at least 3 vertices and 1 face");
  TriangleMesh m;
  m.vertices.reserve(size_t(nv));
  for (long i = 0; i < nv; ++i) {
    if (!next_line(line, ln))
      throw InputError(path + ": truncated after " + std::to_string(i) + " vertices");
    std::istringstream ss(line);
    Vec3d p;
    if (!(ss >> p[0] >> p[1] >> p[2]))
      throw InputError(path + ":" + std::to_string(ln) + ": expected 'x y z'");
    m.vertices.push_back(p);
  }
  for (long f = 0; f < nf; ++f) {
    if (!next_line(line, ln))
      throw InputError(path + ": truncated after " + std::to_string(f) + " faces");
    std::istringstream ss(line);
    long k = 0;
    ss >> k;
    std::vector<std::int32_t> poly(size_t(std::max(0L, k)));
    for (auto& i : poly)
      if (!(ss >> i))
        throw InputError(path + ":" + std::to_string(ln) +
                         ": face has fewer indices than its count");
    add_polygon(m, poly, path + ":" + std::to_string(ln));
  }
  return m;
}

// PLY: ASCII or binary little-endian; vertex x/y/z of any scalar type, faces as a list property.
TriangleMesh read_ply(const std::string& path, std::istream& in) {
  struct Prop {
    std::string name, type, count_type;  // count_type non-empty for lists
  };
  struct Element {
    std::string name;
    long count = 0;
    std::vector<Prop> props;
  };
  std::string line, format;
  std::vector<Element> elems;
  if (!std::getline(in, line) || line.rfind("ply", 0) != 0)
    throw InputError(path + ":1: expected the 'ply' header");
  while (std::getline(in, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ss(line);
    std::string w;
    ss >> w;
    if (w == "format")
      ss >> format;
    else if (w == "element") {
      Element e;
      ss >> e.name >> e.count;
      elems.push_back(e);
    } else if (w == "property") {
      if (elems.empty()) throw InputError(path + ": property before any element");
      Prop p;
      ss >> p.type;
      if (p.type == "list") ss >> p.count_type >> p.type;
      ss >> p.name;
      elems.back().props.push_back(p);
    } else if (w == "end_header")
      break;
  }
  const bool ascii = format == "ascii";
  if (!ascii && format != "binary_little_endian")
    throw InputError(path + ": PLY format '" + format +
                     "' not supported (ascii or binary_little_endian)");
  auto size_of = [&](const std::string& t) -> int {
    if (t == "char" || t == "uchar" || t == "int8" || t == "uint8") return 1;
    if (t == "short" || t == "ushort" || t == "int16" || t == "uint16") return 2;
    if (t == "int" || t == "uint" || t == "float" || t == "int32" || t == "uint32" ||
        t == "float32")
      return 4;
    if (t == "double" || t == "float64") return 8;
    throw InputError(path + ": unknown PLY property type '" + t + "'");
  };
  auto read_value = [&](const std::string& t) -> double {
    if (ascii) {
      double v;
      if (!(in >> v)) throw InputError(path + ": truncated PLY data");
      return v;
    }
    char b[8];
    const int n = size_of(t);
    if (!in.read(b, n)) throw InputError(path + ": truncated PLY data");
    if (t == "char" || t == "int8") return double(*reinterpret_cast<std::int8_t*>(b));
    if (t == "uchar" || t == "uint8") return double(*reinterpret_cast<std::uint8_t*>(b));
    if (t == "short" || t == "int16") {
      std::int16_t v;
      std::memcpy(&v, b, 2);
      return v;
    }
    if (t == "ushort" || t == "uint16") {
      std::uint16_t v;
      std::memcpy(&v, b, 2);
      return v;
    }
    if (t == "int" || t == "int32") {
      std::int32_t v;
      std::memcpy(&v, b, 4);
      return v;
    }
    if (t == "uint" || t == "uint32") {
      std::uint32_t v;
      std::memcpy(&v, b, 4);
      return v;
    }
    if (t == "float" || t == "float32") {
      float v;
      std::memcpy(&v, b, 4);
      return v;
    }
    double v;
    std::memcpy(&v, b, 8);
    return v;
  };
  TriangleMesh m;
  for (const auto& e : elems) {
    for (long i = 0; i < e.count; ++i) {
      Vec3d p = Vec3d::Zero();
      for (const auto& pr : e.props) {
        if (!pr.count_type.empty()) {
          const long k = long(read_value(pr.count_type));
          std::vector<std::int32_t> poly;
          for (long j = 0; j < k; ++j) poly.push_back(std::int32_t(read_value(pr.type)));
          if (e.name == "face" && (pr.name == "vertex_indices" || pr.name == "vertex_index"))
            add_polygon(m, poly, path + ": face " + std::to_string(i));
        } else {
          const double v = read_value(pr.type);
          if (e.name == "vertex") {
            if (pr.name == "x")
              p[0] = v;
            else if (pr.name == "y")
              p[1] = v;
            else if (pr.name == "z")
              p[2] = v;
          }
        }
      }
      if (e.name == "vertex") m.vertices.push_back(p);
    }
  }
  return m;
}

}  // namespace

TriangleMesh load_mesh(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path + ": cannot open mesh file");
  const std::string ext = lower_ext(path);
  TriangleMesh m;
  if (ext == "obj")
    m = read_obj(path, in);
  else if (ext == "off")
    m = read_off(path, in);
  else if (ext == "ply")
    m = read_ply(path, in);
  else
    throw InputError(path + ": unknown mesh format '." + ext + "' (expected .obj, .off or .ply)");
  if (m.triangles.empty()) throw InputError(path + ": mesh has no faces");
  for (const auto& v : m.vertices)
    if (!v.allFinite()) throw InputError(path + ": mesh has a non-finite vertex coordinate");
  return m;
}

}  // namespace amalgam
