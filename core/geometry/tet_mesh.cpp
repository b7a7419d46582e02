#include "core/geometry/tet_mesh.hpp"

#include <cmath>

namespace amalgam {

void tet_barycentres(const TetMesh& m, std::vector<Vec3>& x, std::vector<Real>& volume) {
  x.resize(m.tets.size());
  volume.resize(m.tets.size());
  for (std::size_t k = 0; k < m.tets.size(); ++k) {
    const auto& t = m.tets[k];
    const Vec3d a = m.nodes[std::size_t(t[0])], b = m.nodes[std::size_t(t[1])],
                c = m.nodes[std::size_t(t[2])], d = m.nodes[std::size_t(t[3])];
    x[k] = (0.25 * (a + b + c + d)).cast<Real>();
    volume[k] = Real(std::abs((b - a).dot((c - a).cross(d - a))) / 6);
  }
}

double tet_mean_edge(const TetMesh& m) {
  double sum = 0;
  for (const auto& t : m.tets)
    for (int i = 0; i < 4; ++i)
      for (int j = i + 1; j < 4; ++j)
        sum += (m.nodes[std::size_t(t[i])] - m.nodes[std::size_t(t[j])]).norm();
  return m.tets.empty() ? 0 : sum / (6.0 * double(m.tets.size()));
}

}  // namespace amalgam
