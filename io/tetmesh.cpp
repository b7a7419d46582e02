#include "io/tetmesh.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <fstream>
#include <map>
#include <sstream>

#include "core/errors.hpp"
#include "io/files.hpp"

namespace amalgam {

namespace {

// Lines of a TetGen file without comments (#...) and blank lines, with their line numbers.
struct Lines {
  std::vector<std::pair<int, std::string>> rows;
};
Lines read_lines(const std::string& path) {
  (void)input_file_size(path, "TetGen file");  // a regular file (not a directory or device)
  std::ifstream in(path);
  if (!in) throw InputError(path + ": cannot open TetGen file");
  Lines l;
  std::string s;
  int no = 0;
  while (std::getline(in, s)) {
    ++no;
    const auto hash = s.find('#');
    if (hash != std::string::npos) s.resize(hash);
    if (s.find_first_not_of(" \t\r") == std::string::npos) continue;
    l.rows.emplace_back(no, s);
  }
  return l;
}

[[noreturn]] void fail(const std::string& path, int line, const std::string& what) {
  throw InputError(path + ":" + std::to_string(line) + ": " + what);
}

std::string stem_of(const std::string& path) {
  for (const char* ext : {".node", ".ele"}) {
    const std::string e(ext);
    if (path.size() > e.size() && path.compare(path.size() - e.size(), e.size(), e) == 0)
      return path.substr(0, path.size() - e.size());
  }
  return path;
}

}  // namespace

TetMesh load_tetgen(const std::string& path) {
  const std::string stem = stem_of(path), node_path = stem + ".node", ele_path = stem + ".ele";
  TetMesh m;
  const Lines nl = read_lines(node_path);
  if (nl.rows.empty()) fail(node_path, 1, "empty .node file");
  long long n = 0, dim = 0, nattr = 0, nmark = 0;
  {
    std::istringstream h(nl.rows[0].second);
    if (!(h >> n >> dim >> nattr >> nmark) || n <= 0 || dim != 3 || nattr < 0 ||
        (nmark != 0 && nmark != 1))
      fail(node_path, nl.rows[0].first, "expected header '<points> 3 <attributes> <0|1>'");
  }
  if (static_cast<long long>(nl.rows.size()) - 1 < n)
    fail(node_path, nl.rows.back().first,
         "file ends after " + std::to_string(nl.rows.size() - 1) + " of " + std::to_string(n) +
             " points");
  long long base = 0;
  m.nodes.resize(std::size_t(n));
  for (long long k = 0; k < n; ++k) {
    const auto& [line, text] = nl.rows[std::size_t(k + 1)];
    std::istringstream r(text);
    long long idx;
    double x, y, z;
    if (!(r >> idx >> x >> y >> z) || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z))
      fail(node_path, line, "expected '<index> <x> <y> <z>' with finite coordinates");
    if (k == 0) base = idx;
    if (idx != base + k)
      fail(node_path, line,
           "point index " + std::to_string(idx) + ", expected " + std::to_string(base + k));
    m.nodes[std::size_t(k)] = Vec3d(x, y, z);
  }
  const Lines el = read_lines(ele_path);
  if (el.rows.empty()) fail(ele_path, 1, "empty .ele file");
  long long nt = 0, per = 0, tattr = 0;
  {
    std::istringstream h(el.rows[0].second);
    if (!(h >> nt >> per) || nt <= 0 || (per != 4 && per != 10))
      fail(ele_path, el.rows[0].first, "expected header '<tetrahedra> <4|10> [<attributes>]'");
    h >> tattr;
  }
  if (static_cast<long long>(el.rows.size()) - 1 < nt)
    fail(ele_path, el.rows.back().first,
         "file ends after " + std::to_string(el.rows.size() - 1) + " of " + std::to_string(nt) +
             " tetrahedra");
  m.tets.resize(std::size_t(nt));
  // A tetrahedron given twice would put two particles in one place and two copies of its faces
  // in the crack mesh: refused with both lines named.
  std::map<std::array<std::int32_t, 4>, int> seen;
  for (long long k = 0; k < nt; ++k) {
    const auto& [line, text] = el.rows[std::size_t(k + 1)];
    std::istringstream r(text);
    long long idx, v[4];
    if (!(r >> idx >> v[0] >> v[1] >> v[2] >> v[3]))
      fail(ele_path, line, "expected '<index> <n1> <n2> <n3> <n4>'");
    for (int c = 0; c < 4; ++c) {
      if (v[c] < base || v[c] >= base + n)
        fail(ele_path, line,
             "node " + std::to_string(v[c]) + " does not exist (the .node file numbers " +
                 std::to_string(base) + ".." + std::to_string(base + n - 1) + ")");
      m.tets[std::size_t(k)][std::size_t(c)] = std::int32_t(v[c] - base);
    }
    const auto& t = m.tets[std::size_t(k)];
    const Vec3d a = m.nodes[std::size_t(t[0])];
    const double vol =
        std::abs((m.nodes[std::size_t(t[1])] - a)
                     .dot((m.nodes[std::size_t(t[2])] - a).cross(m.nodes[std::size_t(t[3])] - a))) /
        6;
    if (!(vol > 0)) fail(ele_path, line, "tetrahedron " + std::to_string(idx) + " has zero volume");
    std::array<std::int32_t, 4> key = t;
    std::sort(key.begin(), key.end());
    const auto [it, fresh] = seen.emplace(key, line);
    if (!fresh)
      fail(ele_path, line,
           "tetrahedron " + std::to_string(idx) + " repeats the one on line " +
               std::to_string(it->second) + " (same four nodes)");
  }
  return m;
}

}  // namespace amalgam
