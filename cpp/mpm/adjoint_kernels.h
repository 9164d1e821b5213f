// Vector-Jacobian products of the per-particle math in kernels.h, for Solver::step_adjoint:
// the B-spline weights' derivatives, and for the elastic materials the map (F, mu, lambda) ->
// tau transposed: given tau_bar = dL/dtau, dL/dF, dL/dmu, dL/dlambda.
//   fixed corotated: tau = 2 mu (F - R) F^T + lambda (J - 1) J I, R = U V^T the polar rotation;
//   dR = R W with W = V (K~_ij / (sigma_i + sigma_j)) V^T, K~ = V^T (R^T dF - dF^T R) V (the
//   skew part of the polar decomposition's differential, e.g. Papadopoulo and Lourakis 2000,
//   in the form of Stomakhin et al. 2012's supplement); no 1 / (sigma_i - sigma_j) terms, so it is
//   regular at F = I.
//   neo-Hookean: tau = mu F F^T + (lambda_s (J - 1) J - mu J) I, lambda_s = lambda + mu.
//   water: tau = -J p(J) I and the projection F <- J^(1/d) I, both functions of J alone.
// dJ = cof(F) : dF with cof(F) = J F^-T written without the inverse.
#pragma once

#include "mpm/kernels.h"

namespace kinema::mpm {

// d w_k / d fx of bspline_weights.
inline void bspline_derivatives(Scalar fx, Scalar dw[3]) {
  dw[0] = fx - 1.5;
  dw[1] = -2 * (fx - 1.0);
  dw[2] = fx - 0.5;
}

inline Mat<2> cofactor(const Mat<2>& F) {
  Mat<2> c;
  c << F(1, 1), -F(1, 0), -F(0, 1), F(0, 0);
  return c;
}

inline Mat<3> cofactor(const Mat<3>& F) {
  Mat<3> c;
  c.row(0) = F.row(1).cross(F.row(2));
  c.row(1) = F.row(2).cross(F.row(0));
  c.row(2) = F.row(0).cross(F.row(1));
  return c;
}

// dL/dF of R = U V^T (the polar rotation of F = U diag(sigma) V^T) given R_bar = dL/dR.
template <int D>
Mat<D> polar_rotation_vjp(const Svd<D>& s, const Mat<D>& R_bar) {
  const Mat<D> R = s.U * s.V.transpose();
  Mat<D> H = s.V.transpose() * R.transpose() * R_bar * s.V;
  for (int i = 0; i < D; ++i)
    for (int j = 0; j < D; ++j) H(i, j) = i == j ? 0 : H(i, j) / (s.sigma(i) + s.sigma(j));
  const Mat<D> P = s.V * H * s.V.transpose();
  return R * (P - P.transpose());
}

// Accumulates the products of corotated_tau: F_bar += dL/dF, and returns dL/dmu, dL/dlambda.
template <int D>
void corotated_tau_vjp(const Mat<D>& F, const Svd<D>& s, Scalar mu, Scalar lambda, const Mat<D>& tau_bar,
                       Mat<D>& F_bar, Scalar& mu_bar, Scalar& lambda_bar) {
  const Scalar J = s.sigma.prod();
  const Mat<D> R = s.U * s.V.transpose();
  const Scalar trace = tau_bar.trace();
  F_bar += 2 * mu * ((tau_bar + tau_bar.transpose()) * F - tau_bar.transpose() * R) +
           polar_rotation_vjp<D>(s, -2 * mu * tau_bar * F) + (lambda * (2 * J - 1) * trace) * cofactor(F);
  mu_bar = 2 * (tau_bar.cwiseProduct(F * F.transpose() - R * F.transpose())).sum();
  lambda_bar = trace * (J - 1) * J;
}

template <int D>
void neohookean_tau_vjp(const Mat<D>& F, Scalar mu, Scalar lambda, const Mat<D>& tau_bar, Mat<D>& F_bar,
                        Scalar& mu_bar, Scalar& lambda_bar) {
  const Scalar J = F.determinant(), trace = tau_bar.trace();
  F_bar += mu * (tau_bar + tau_bar.transpose()) * F + (trace * ((lambda + mu) * (2 * J - 1) - mu)) * cofactor(F);
  mu_bar = tau_bar.cwiseProduct(F * F.transpose()).sum() + trace * ((J - 1) * J - J);
  lambda_bar = trace * (J - 1) * J;
}

// Water (kernels.h, water_tau): tau = -J p I, p = K / gamma (Jc^-gamma - 1), Jc = max(J, 1e-6).
// F_bar += dL/dF; returns dL/dK. Below the clamp p is constant (the branch taken).
template <int D>
Scalar water_tau_vjp(const Mat<D>& F, Scalar bulk, Scalar gamma, const Mat<D>& tau_bar, Mat<D>& F_bar) {
  const Scalar J = F.determinant(), Jc = std::max(J, 1e-6), J_gamma = std::pow(Jc, -gamma);
  const Scalar p = bulk / gamma * (J_gamma - 1), dp_dJ = J > 1e-6 ? -bulk * J_gamma / Jc : 0;
  const Scalar trace = tau_bar.trace();
  F_bar += (-trace * (p + J * dp_dJ)) * cofactor(F);
  return -trace * J * (J_gamma - 1) / gamma;
}

// Water's projection F <- Jc^(1/d) I (solver.cpp, plasticity), transposed at the trial F.
template <int D>
Mat<D> water_projection_vjp(const Mat<D>& F, const Mat<D>& F_bar) {
  const Scalar J = F.determinant();
  if (!(J > 1e-6)) return Mat<D>::Zero();
  const Scalar root = D == 2 ? std::sqrt(J) : std::cbrt(J);
  return (F_bar.trace() * root / (D * J)) * cofactor(F);
}

// d(mu, lambda) / d(E, nu) of lame_parameters, transposed.
inline void lame_parameters_vjp(Scalar E, Scalar nu, Scalar mu_bar, Scalar lambda_bar, Scalar& E_bar, Scalar& nu_bar) {
  const Scalar q = (1 + nu) * (1 - 2 * nu);
  E_bar = mu_bar / (2 * (1 + nu)) + lambda_bar * nu / q;
  nu_bar = -mu_bar * E / (2 * (1 + nu) * (1 + nu)) + lambda_bar * E * (1 + 2 * nu * nu) / (q * q);
}

}  // namespace kinema::mpm
