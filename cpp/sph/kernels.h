// Per-particle SPH math: the cubic spline kernel of the course notes (Koschier, Bender,
// Solenthaler and Teschner, "Smoothed Particle Hydrodynamics Techniques for the Physics Based
// Simulation of Fluids and Solids", Eurographics tutorial 2019, eq. 4), with support radius h:
//   W(q) = sigma_d * { 6 (q^3 - q^2) + 1  (0 <= q <= 1/2);  2 (1 - q)^3  (1/2 < q <= 1);  0 },
//   q = r / h,  sigma_2 = 40 / (7 pi h^2),  sigma_3 = 8 / (pi h^3),
// its radial derivatives and gradient, and the symmetric pair terms the solvers share.
#pragma once

#include <Eigen/Core>
#include <cmath>

#include "core/types.h"

namespace kinema::sph {

constexpr Scalar kPi = 3.14159265358979323846;

// Normalisation sigma_d of the cubic spline in d dimensions for support radius h.
inline Scalar kernel_sigma(int d, Scalar h) {
  return d == 2 ? 40.0 / (7.0 * kPi * h * h) : 8.0 / (kPi * h * h * h);
}

// W(r, h) for d = 2 or 3.
inline Scalar kernel_w(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h);
  if (q <= 0.5) return s * (6 * (q * q * q - q * q) + 1);
  const Scalar t = 1 - q;
  return s * 2 * t * t * t;
}

// dW/dr.
inline Scalar kernel_dw(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h) / h;
  if (q <= 0.5) return s * 6 * (3 * q * q - 2 * q);
  const Scalar t = 1 - q;
  return -s * 6 * t * t;
}

// d^2W/dr^2.
inline Scalar kernel_d2w(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h) / (h * h);
  if (q <= 0.5) return s * 6 * (6 * q - 2);
  return s * 12 * (1 - q);
}

// The kernel with its constants precomputed, as the solvers' inner loops use it.
template <int D>
struct CubicSpline {
  using Vec = Eigen::Matrix<Scalar, D, 1>;

  explicit CubicSpline(Scalar h_) : h(h_), inv_h(1 / h_), sigma(kernel_sigma(D, h_)) {}

  // Both pieces are evaluated and one is selected, so that the inner loops do not branch on
  // q <= 1/2.
  Scalar w(Scalar r) const {
    const Scalar q = r * inv_h;
    const Scalar t = 1 - q;
    const Scalar inner = sigma * (6 * (q * q * q - q * q) + 1);
    const Scalar outer = sigma * 2 * t * t * t;
    return q >= 1 ? 0 : q <= 0.5 ? inner : outer;
  }
  Scalar w0() const { return sigma; }

  // (dW/dr) / r at distance r, so that grad_i W(x_i - x_j) = grad_factor(r) (x_i - x_j); zero
  // at r = 0, where the direction is undefined, and outside the support.
  Scalar grad_factor(Scalar r) const {
    if (r <= 0) return 0;
    const Scalar q = r * inv_h;
    const Scalar inner = sigma * inv_h * 6 * (3 * q * q - 2 * q);
    const Scalar outer = -sigma * inv_h * 6 * (1 - q) * (1 - q);
    return q >= 1 ? 0 : (q <= 0.5 ? inner : outer) / r;
  }

  // grad_i W(x_i - x_j) for xij = x_i - x_j.
  Vec grad(const Vec& xij) const { return grad_factor(std::sqrt(xij.squaredNorm())) * xij; }

  Scalar h, inv_h, sigma;
};

// Tait's equation of state (Becker and Teschner 2007, eq. 6), p = B ((rho/rho0)^gamma - 1),
// with negative pressures clamped to zero: they would pull free-surface particles into
// clumps (tensile instability).
inline Scalar tait_pressure(Scalar rho, Scalar rho0, Scalar B, Scalar gamma) {
  const Scalar ratio = rho / rho0;
  if (ratio <= 1) return 0;
  return B * (std::pow(ratio, gamma) - 1);
}

// Laminar viscosity term of Morris et al. 1997 in the form of Monaghan 2005 / Koschier et al.
// 2019 eq. 33: the acceleration of i from j for kinematic viscosity nu,
//   2 (d + 2) nu (m_j / rho_j) (v_ij . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij.
template <int D>
inline Eigen::Matrix<Scalar, D, 1> viscosity_term(const Eigen::Matrix<Scalar, D, 1>& xij,
                                                 const Eigen::Matrix<Scalar, D, 1>& vij,
                                                 const Eigen::Matrix<Scalar, D, 1>& grad_w,
                                                 Scalar volume_j, Scalar nu, Scalar h) {
  const Scalar c = 2 * (D + 2) * nu * volume_j * vij.dot(xij) / (xij.squaredNorm() + 0.01 * h * h);
  return c * grad_w;
}

}  // namespace kinema::sph
