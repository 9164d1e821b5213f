// Per-spring math of Hooke springs between vertices i and j (Baraff & Witkin, "Large steps in
// cloth simulation", SIGGRAPH 1998, section 4; Choi & Ko 2002 for the definiteness of the
// transverse term). With d = x_j - x_i, l = |d|, n = d / l, rest length L and stiffness k:
//   energy   U = k/2 (l - L)^2
//   force    f_i = k (l - L) n = -f_j
//   Jacobian df_i/dx_j = k [ n n^T + (1 - L/l) (I - n n^T) ] =: k S,  df_i/dx_i = -k S
// S is indefinite for a compressed spring (l < L); `clamp` drops the negative transverse
// term, which makes the stiffness positive semidefinite (the exact Jacobian otherwise).
// Damping along the spring: f_i = c ((v_j - v_i) . n) n, df_i/dv_j = c n n^T.
// The adjoint of the implicit step needs the derivative of a bilinear form of these matrices:
//   d/dd [mu^T S w] with S = (1 - L/l) I + L d d^T / l^3 (unclamped), d d^T / l^2 (clamped, l < L)
//   = L (mu.w) d / l^3 + L [(w.d) mu + (mu.d) w] / l^3 - 3 L (mu.d)(w.d) d / l^5,
//   d/dd [(mu.d)(w.d) / l^2] = [(w.d) mu + (mu.d) w] / l^2 - 2 (mu.d)(w.d) d / l^4.
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
  const Vec<D> n = d * (1 / l);  // one division (spring_pass.h computes n the same way)
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

// Whether spring_jacobian(d, L, clamp) dropped the transverse term (its t = 1 - L/l < 0).
template <int D>
bool transverse_clamped(const Vec<D>& d, Scalar L, bool clamp) {
  return clamp && d.norm() < L;
}

// d/dd [(mu.d)(w.d) / l^2] = d/dd [mu^T n n^T w] (header); 0 for a zero-length spring.
template <int D>
Vec<D> spring_damping_vjp(const Vec<D>& d, const Vec<D>& mu, const Vec<D>& w) {
  const Scalar l2 = d.squaredNorm();
  if (l2 == 0) return Vec<D>::Zero();
  const Scalar md = mu.dot(d), wd = w.dot(d);
  return (wd * mu + md * w) / l2 - 2 * md * wd / (l2 * l2) * d;
}

// d/dd [mu^T S w] for S = spring_jacobian(d, L, clamp) (header); 0 for a zero-length spring.
template <int D>
Vec<D> spring_jacobian_vjp(const Vec<D>& d, Scalar L, bool clamp, const Vec<D>& mu, const Vec<D>& w) {
  const Scalar l = d.norm();
  if (l == 0) return Vec<D>::Zero();
  if (transverse_clamped<D>(d, L, clamp)) return spring_damping_vjp<D>(d, mu, w);
  const Scalar md = mu.dot(d), wd = w.dot(d), l3 = l * l * l;
  return L / l3 * (mu.dot(w) * d + wd * mu + md * w - 3 * md * wd / (l * l) * d);
}

// d/dL [mu^T S w] = -(mu^T (I - n n^T) w) / l (0 where clamped or zero-length).
template <int D>
Scalar spring_jacobian_dL(const Vec<D>& d, Scalar L, bool clamp, const Vec<D>& mu, const Vec<D>& w) {
  const Scalar l = d.norm();
  if (l == 0 || transverse_clamped<D>(d, L, clamp)) return 0;
  const Vec<D> n = d / l;
  return -(mu.dot(w) - mu.dot(n) * w.dot(n)) / l;
}

}  // namespace kinema::massspring
