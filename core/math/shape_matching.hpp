// Rigid shape matching (Kabsch; Mueller et al. 2005's shape matching without scaling): the mean
// distance between two point sets after the best rigid alignment, the rest-state error of enriched
// MPM's Table 1 and A-ULMPM's twisting bar.
#pragma once

#include <Eigen/SVD>
#include <vector>

#include "core/math/types.hpp"

namespace amalgam {

// Mean |R (now_p - c_now) + c_rest - rest_p| with centroids c and the rotation R from the SVD of
// the cross-covariance (a reflection excluded). Points correspond by index.
inline double rest_shape_deviation(const std::vector<Vec3d>& rest, const std::vector<Vec3d>& now) {
  Vec3d cr = Vec3d::Zero(), cn = Vec3d::Zero();
  for (size_t p = 0; p < rest.size(); ++p) cr += rest[p], cn += now[p];
  cr /= double(rest.size()), cn /= double(rest.size());
  Mat3d H = Mat3d::Zero();
  for (size_t p = 0; p < rest.size(); ++p) H += (now[p] - cn) * (rest[p] - cr).transpose();
  Eigen::JacobiSVD<Mat3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Mat3d D = Mat3d::Identity();
  D(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1 : 1;
  const Mat3d R = svd.matrixV() * D * svd.matrixU().transpose();  // rotates now onto rest
  double sum = 0;
  for (size_t p = 0; p < rest.size(); ++p) sum += (R * (now[p] - cn) + cr - rest[p]).norm();
  return sum / double(rest.size());
}

}  // namespace amalgam
