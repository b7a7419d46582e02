// Mesh file readers: OBJ, OFF, PLY (ASCII or binary little-endian) and STL (ASCII or binary).
// Files are untrusted: every count a header claims is checked against the bytes the file has
// before anything is sized by it, and every index against the range it must lie in.
#include "io/mesh.hpp"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <iomanip>
#include <limits>
#include <sstream>
#include <unordered_map>

#include "core/errors.hpp"
#include "core/hash.hpp"
#include "io/files.hpp"

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
        errno = 0;
        const long long idx = std::strtoll(tok.c_str(), nullptr, 10);  // "i", "i/t", "i//n", ...
        if (idx == 0) throw InputError(where + ": bad face index '" + tok + "'");
        const long long i0 = idx > 0 ? idx - 1 : (long long)m.vertices.size() + idx;
        if (errno == ERANGE || i0 < 0 || i0 >= (long long)m.vertices.size())
          throw InputError(where + ": face index '" + tok + "' out of range (" +
                           std::to_string(m.vertices.size()) + " vertices so far)");
        poly.push_back(std::int32_t(i0));
      }
      add_polygon(m, poly, where);
    }
  }
  return m;
}

TriangleMesh read_off(const std::string& path, std::istream& in, std::uint64_t bytes) {
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
  // A vertex line takes at least 6 bytes ("0 0 0\n"), a face line 8 ("3 0 1 2\n").
  if (std::uint64_t(nv) > bytes / 6 || std::uint64_t(nf) > bytes / 8 ||
      std::uint64_t(nv) * 6 + std::uint64_t(nf) * 8 > bytes)
    throw InputError(path + ": the header claims " + std::to_string(nv) + " vertices and " +
                     std::to_string(nf) + " faces, more than a file of " + std::to_string(bytes) +
                     " bytes can hold");
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
    if (k < 3 || std::size_t(k) > line.size() / 2)
      throw InputError(path + ":" + std::to_string(ln) + ": a face of " + std::to_string(k) +
                       " vertices on a line of " + std::to_string(line.size()) + " bytes");
    std::vector<std::int32_t> poly(static_cast<std::size_t>(k));
    for (auto& i : poly)
      if (!(ss >> i))
        throw InputError(path + ":" + std::to_string(ln) +
                         ": face has fewer indices than its count");
    add_polygon(m, poly, path + ":" + std::to_string(ln));
  }
  return m;
}

// PLY: ASCII or binary little-endian; vertex x/y/z of any scalar type, faces as a list property.
TriangleMesh read_ply(const std::string& path, std::istream& in, std::uint64_t bytes) {
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
      if (!(ss >> e.name >> e.count))
        throw InputError(path + ": expected 'element <name> <count>', got '" + line + "'");
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
  const std::streamoff header_end = in.tellg();
  const std::uint64_t body = header_end < 0 ? 0 : bytes - std::uint64_t(header_end);
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
  // What each element's count claims, against the bytes after the header: a binary record takes
  // its fixed properties plus each list's count, an ASCII value at least 2 bytes ("0 ").
  double claimed = 0;
  for (const auto& e : elems) {
    if (e.count < 0) throw InputError(path + ": element '" + e.name + "' has a negative count");
    double record = 0;
    for (const auto& pr : e.props)
      record += ascii ? 2 : double(size_of(pr.count_type.empty() ? pr.type : pr.count_type));
    claimed += double(e.count) * std::max(record, 1.0);
  }
  if (claimed > double(body)) {
    std::ostringstream os;
    os << path << ": the header's element counts need at least " << std::setprecision(15) << claimed
       << " bytes, the file has " << body << " after its header";
    throw InputError(os.str());
  }
  TriangleMesh m;
  for (const auto& e : elems) {
    for (long i = 0; i < e.count; ++i) {
      Vec3d p = Vec3d::Zero();
      for (const auto& pr : e.props) {
        if (!pr.count_type.empty()) {
          const double kd = read_value(pr.count_type);
          if (!(kd >= 0) || kd * (ascii ? 2 : size_of(pr.type)) > double(body))
            throw InputError(path + ": " + e.name + " " + std::to_string(i) + ": a list of " +
                             std::to_string(kd) + " values, more than the file holds");
          const long k = long(kd);
          std::vector<std::int32_t> poly;
          for (long j = 0; j < k; ++j) {
            const double idx = read_value(pr.type);
            if (!(idx >= 0 && idx < 2147483647.0))
              throw InputError(path + ": " + e.name + " " + std::to_string(i) + ": index " +
                               std::to_string(idx) + " out of range");
            poly.push_back(std::int32_t(idx));
          }
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

// STL: binary (80-byte header, u32 count, 50 bytes per triangle: normal, 3 vertices, attribute)
// or ASCII ("solid ... facet ... vertex x y z ... endsolid"). STL repeats each vertex per
// triangle: equal coordinates are welded into one vertex, so the mesh's edges are shared and a
// closed STL is watertight.
class Welder {
 public:
  explicit Welder(TriangleMesh& m) : m_(m) {}
  std::int32_t add(float x, float y, float z) {
    std::array<std::uint32_t, 3> key;
    const float v[3] = {x == 0 ? 0.0f : x, y == 0 ? 0.0f : y, z == 0 ? 0.0f : z};  // -0 = 0
    std::memcpy(key.data(), v, sizeof v);
    const auto [it, fresh] = index_.emplace(key, std::int32_t(m_.vertices.size()));
    if (fresh) m_.vertices.emplace_back(v[0], v[1], v[2]);
    return it->second;
  }

 private:
  struct Hash {
    std::size_t operator()(const std::array<std::uint32_t, 3>& k) const {
      return std::size_t(fnv1a64(k.data(), sizeof k));
    }
  };
  TriangleMesh& m_;
  std::unordered_map<std::array<std::uint32_t, 3>, std::int32_t, Hash> index_;
};

TriangleMesh read_stl(const std::string& path, std::istream& in, std::uint64_t bytes) {
  TriangleMesh m;
  Welder weld(m);
  char head[84] = {};
  in.read(head, 84);
  const bool has_count = in.gcount() == 84;
  std::uint32_t count = 0;
  if (has_count) std::memcpy(&count, head + 80, 4);
  // Binary when the size is exactly what the count says (a binary header may begin "solid").
  if (has_count && bytes == 84 + 50 * std::uint64_t(count)) {
    m.triangles.reserve(count);
    char rec[50];
    for (std::uint32_t t = 0; t < count; ++t) {
      if (!in.read(rec, 50))
        throw InputError(path + ": truncated after " + std::to_string(t) + " triangles");
      float f[12];
      std::memcpy(f, rec, sizeof f);
      std::array<std::int32_t, 3> tri;
      for (int c = 0; c < 3; ++c)
        tri[size_t(c)] = weld.add(f[3 + 3 * c], f[4 + 3 * c], f[5 + 3 * c]);
      m.triangles.push_back(tri);
    }
    return m;
  }
  if (std::strncmp(head, "solid", 5) != 0)
    throw InputError(path + ": neither a binary STL (" + std::to_string(bytes) +
                     " bytes, not 84 + 50 x " + std::to_string(count) +
                     ") nor an ASCII one (no 'solid' at the start)");
  in.clear();
  in.seekg(0);
  std::string line;
  int ln = 0;
  std::vector<std::int32_t> poly;
  while (std::getline(in, line)) {
    ++ln;
    std::istringstream ss(line);
    std::string w;
    ss >> w;
    if (w == "vertex") {
      double x, y, z;
      if (!(ss >> x >> y >> z))
        throw InputError(path + ":" + std::to_string(ln) + ": expected 'vertex x y z'");
      poly.push_back(weld.add(float(x), float(y), float(z)));
    } else if (w == "endloop") {
      add_polygon(m, poly, path + ":" + std::to_string(ln));
      poly.clear();
    }
  }
  return m;
}

}  // namespace

namespace {
TriangleMesh read_mesh(std::istream& in, std::uint64_t bytes, const std::string& path) {
  const std::string ext = lower_ext(path);
  TriangleMesh m;
  if (ext == "obj")
    m = read_obj(path, in);
  else if (ext == "off")
    m = read_off(path, in, bytes);
  else if (ext == "ply")
    m = read_ply(path, in, bytes);
  else if (ext == "stl")
    m = read_stl(path, in, bytes);
  else
    throw InputError(path + ": unknown mesh format '." + ext +
                     "' (expected .obj, .off, .ply or .stl)");
  if (m.vertices.size() > std::size_t(std::numeric_limits<std::int32_t>::max()))
    throw InputError(path + ": more vertices than 32-bit indices address");
  if (m.triangles.empty()) throw InputError(path + ": mesh has no faces");
  for (const auto& v : m.vertices)
    if (!v.allFinite()) throw InputError(path + ": mesh has a non-finite vertex coordinate");
  return m;
}
}  // namespace

TriangleMesh load_mesh(const std::string& path) {
  const std::string ext = lower_ext(path);
  if (ext != "obj" && ext != "off" && ext != "ply" && ext != "stl")
    throw InputError(path + ": unknown mesh format '." + ext +
                     "' (expected .obj, .off, .ply or .stl)");
  const std::uint64_t bytes = input_file_size(path, "mesh file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(path + ": cannot open mesh file");
  return read_mesh(in, bytes, path);
}

TriangleMesh parse_mesh(const std::string& bytes, const std::string& name) {
  std::istringstream in(bytes);
  return read_mesh(in, bytes.size(), name);
}

}  // namespace amalgam
