// Per-spring math of Hooke springs between vertices i and j (Baraff & Witkin, "Large steps in
// cloth simulation", SIGGRAPH 1998, section 4; Choi & Ko 2002 for the definiteness of the
// transverse term). With d = x_j - x_i, l = |d|, n = d / l, rest length L and stiffness k:
//   energy   U = k/2 (l - L)^2
//   force    f_i = k (l - L) n = -f_j
//   Jacobian df_i/dx_j = k [ n n^T + (1 - L/l) (I - n n^T) ] =: k S,  df_i/dx_i = -k S
// S is indefinite for a compressed spring (l < L); `clamp` drops the negative transverse
// term, which makes the stiffness positive semidefinite (the exact Jacobian otherwise).
// Damping along the spring: f_i = c ((v_j - v_i) . n) n, df_i/dv_j = c n n^T.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>

#include "core/types.h"

namespace kinema::massspring {

template <int D>
using Vec = Eigen::Matrix<Scalar, D, 1>;
template <int D>
using Mat = Eigen::Matrix<Scalar, D, D>;

template <int D>
Scalar spring_energy(const Vec<D>& d, Scalar k, Scalar L) {
  const Scalar l = d.norm();
  return k / 2 * (l - L) * (l - L);
}

// Elastic plus damping force on vertex i (the force on j is its negative).
template <int D>
Vec<D> spring_force(const Vec<D>& d, const Vec<D>& dv, Scalar k, Scalar L, Scalar c) {
  const Scalar l = d.norm();
  if (l == 0) return Vec<D>::Zero();  // direction undefined: no elastic or damping force
  const Vec<D> n = d / l;
  return (k * (l - L) + c * dv.dot(n)) * n;
}

// S of the header (df_i/dx_j = k S); n n^T alone for a zero-length spring.
template <int D>
Mat<D> spring_jacobian(const Vec<D>& d, Scalar L, bool clamp) {
  const Scalar l = d.norm();
  if (l == 0) return Mat<D>::Identity();
  const Vec<D> n = d / l;
  const Mat<D> nn = n * n.transpose();
  Scalar t = 1 - L / l;
  if (clamp) t = std::max<Scalar>(t, 0);
  return nn + t * (Mat<D>::Identity() - nn);
}

template <int D>
Mat<D> spring_damping(const Vec<D>& d) {
  const Scalar l = d.norm();
  if (l == 0) return Mat<D>::Zero();
  const Vec<D> n = d / l;
  return n * n.transpose();
}

}  // namespace kinema::massspring
