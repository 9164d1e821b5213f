// Per-particle math of the material point method, as free functions templated on the dimension:
// quadratic B-spline weights, the signed SVD, and for every material its Kirchhoff stress
// tau = P(F) F^T (what the MLS-MPM force needs, Hu et al. 2018, eq. 16 with D^-1 = 4 / h^2) and
// its plastic return mapping. F is the elastic deformation gradient; all stresses are
// symmetric by construction, so APIC conserves angular momentum (Jiang et al. 2015, Sec. 5.3).
#pragma once

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "core/types.h"
#include "mpm/model.h"

namespace kinema::mpm {

template <int D>
using Vec = Eigen::Matrix<Scalar, D, 1>;
template <int D>
using Mat = Eigen::Matrix<Scalar, D, D>;

// Quadratic B-spline weights of the 3 nodes base, base+1, base+2 along one axis, for the
// particle at fx = x/h - base in [0.5, 1.5) (Jiang et al. 2016 course notes, eq. 123).
inline void bspline_weights(Scalar fx, Scalar w[3]) {
  const Scalar a = 1.5 - fx, b = fx - 1.0, c = fx - 0.5;
  w[0] = 0.5 * a * a;
  w[1] = 0.75 - b * b;
  w[2] = 0.5 * c * c;
}

// Signed SVD F = U diag(sigma) V^T with U, V rotations (det +1); a reflection shows as a
// negative last singular value (Irving et al. 2004's convention, which keeps the corotated
// rotation R = U V^T proper).
template <int D>
struct Svd {
  Mat<D> U, V;
  Vec<D> sigma;
};

// 2D: F = R S by the closed-form polar decomposition (R's cosine and sine are the normalised
// (F00 + F11, F10 - F01)), then S = W diag(s) W^T by the closed-form eigenvectors of a symmetric
// 2x2 matrix; no trigonometric calls (and sqrt, not hypot: deformation gradients are O(1)).
inline Svd<2> svd(const Mat<2>& F) {
  const Scalar a = F(0, 0) + F(1, 1), b = F(1, 0) - F(0, 1), r = std::sqrt(a * a + b * b);
  const Scalar cr = r > 0 ? a / r : 1, sr = r > 0 ? b / r : 0;
  Mat<2> R;
  R << cr, -sr, sr, cr;
  const Mat<2> S = R.transpose() * F;
  const Scalar p = S(0, 0), q = 0.5 * (S(0, 1) + S(1, 0)), t = S(1, 1);
  const Scalar half = 0.5 * (p - t), root = std::sqrt(half * half + q * q), mid = 0.5 * (p + t);
  // Eigenvector of the larger eigenvalue mid + root: (half + root, q) or, without
  // cancellation when half < 0, (q, root - half).
  Scalar ex = half >= 0 ? half + root : q, ey = half >= 0 ? q : root - half;
  const Scalar en = std::sqrt(ex * ex + ey * ey);
  if (en > 0) {
    ex /= en;
    ey /= en;
  } else {
    ex = 1;
    ey = 0;
  }
  Svd<2> res;
  res.V << ex, -ey, ey, ex;
  res.sigma << mid + root, mid - root;
  res.U = R * res.V;
  return res;
}

// 3D: V from the closed-form eigenvectors of F^T F (Eigen's computeDirect), U by Gram-Schmidt
// on F V, and sigma_i = u_i . F v_i (signed on the smallest one).
inline Svd<3> svd(const Mat<3>& F) {
  Eigen::SelfAdjointEigenSolver<Mat<3>> eig;
  eig.computeDirect(F.transpose() * F);
  Svd<3> r;
  // Eigenvalues come ascending; order the singular values descending.
  r.V.col(0) = eig.eigenvectors().col(2);
  r.V.col(1) = eig.eigenvectors().col(1);
  r.V.col(2) = r.V.col(0).cross(r.V.col(1));
  Vec<3> u0 = F * r.V.col(0);
  Scalar s0 = u0.norm();
  if (!(s0 > 1e-30)) {  // F = 0 (or not finite): any rotation will do
    r.U.setIdentity();
    r.V.setIdentity();
    r.sigma.setZero();
    r.sigma(0) = s0;
    return r;
  }
  u0 /= s0;
  Vec<3> u1 = F * r.V.col(1);
  u1 -= u0.dot(u1) * u0;
  Scalar s1 = u1.norm();
  if (s1 > 1e-14 * s0) {
    u1 /= s1;
  } else {  // rank one: any unit vector orthogonal to u0
    const Vec<3> e = std::abs(u0(0)) < 0.9 ? Vec<3>::UnitX() : Vec<3>::UnitY();
    u1 = (e - e.dot(u0) * u0).normalized();
    s1 = u1.dot(F * r.V.col(1));
  }
  r.U.col(0) = u0;
  r.U.col(1) = u1;
  r.U.col(2) = u0.cross(u1);
  r.sigma << s0, s1, r.U.col(2).dot(F * r.V.col(2));
  return r;
}

// Fixed-corotated elasticity (Stomakhin et al. 2012, eq. 2; 2013, eq. 5):
//   P = 2 mu (F - R) + lambda (J - 1) J F^-T, tau = 2 mu (F F^T - U Sigma U^T) + lambda (J - 1) J I.
template <int D>
Mat<D> corotated_tau(const Mat<D>& F, const Svd<D>& s, Scalar mu, Scalar lambda) {
  const Scalar J = s.sigma.prod();
  Mat<D> tau = 2 * mu * (F * F.transpose() - s.U * s.sigma.asDiagonal() * s.U.transpose());
  tau.diagonal().array() += lambda * (J - 1) * J;
  return tau;
}

// The same stress in 2D from the polar rotation alone: U Sigma U^T = F R^T with R = U V^T the
// rotation of F's polar decomposition, whose cosine and sine are the normalised
// (F00 + F11, F10 - F01) (as in svd above), and J = det F: no eigenvectors needed.
inline Mat<2> corotated_tau(const Mat<2>& F, Scalar mu, Scalar lambda) {
  const Scalar a = F(0, 0) + F(1, 1), b = F(1, 0) - F(0, 1), r = std::sqrt(a * a + b * b);
  const Scalar c = r > 0 ? a / r : 1, s = r > 0 ? b / r : 0;
  Mat<2> R;
  R << c, -s, s, c;
  const Scalar J = F.determinant();
  Mat<2> tau = 2 * mu * (F - R) * F.transpose();
  tau.diagonal().array() += lambda * (J - 1) * J;
  return tau;
}

// Stable neo-Hookean (Smith, de Goes and Kim 2018, eq. 13 without the log barrier):
//   Psi = mu/2 (tr(F^T F) - d) + lambda_s/2 (J - a)^2, a = 1 + mu/lambda_s, lambda_s = lambda + mu
// (the remapping that gives the Lame parameters' linear response, their Sec. 3.4), so
//   tau = mu F F^T + lambda_s (J - a) J I = mu (F F^T - J I) + lambda_s (J - 1) J I,
// the second form exactly 0 at F = I. Defined and smooth for inverted F (J <= 0).
template <int D>
Mat<D> neohookean_tau(const Mat<D>& F, Scalar mu, Scalar lambda) {
  const Scalar ls = lambda + mu, J = F.determinant();
  Mat<D> tau = mu * F * F.transpose();
  tau.diagonal().array() += ls * (J - 1) * J - mu * J;
  return tau;
}

// Hencky (St. Venant-Kirchhoff in log strain) stress of sand (Klar et al. 2016, eq. 26):
//   tau = U (2 mu eps + lambda tr(eps) I) U^T, eps = log(Sigma).
template <int D>
Mat<D> hencky_tau(const Svd<D>& s, Scalar mu, Scalar lambda) {
  const Vec<D> eps = s.sigma.array().abs().max(1e-12).log().matrix();
  const Vec<D> t = 2 * mu * eps + Vec<D>::Constant(lambda * eps.sum());
  return s.U * t.asDiagonal() * s.U.transpose();
}

// Weakly compressible water: Tait pressure p = K / gamma (J^-gamma - 1) and tau = -J p I.
template <int D>
Mat<D> water_tau(Scalar J, Scalar bulk, Scalar gamma) {
  const Scalar Jc = std::max(J, 1e-6);
  const Scalar inv = 1 / Jc;
  // J^-gamma; the usual exponent 7 by multiplication, several times cheaper than pow.
  const Scalar J_gamma = gamma == 7 ? (inv * inv * inv) * (inv * inv * inv) * inv : std::pow(inv, gamma);
  const Scalar p = bulk / gamma * (J_gamma - 1);
  return Mat<D>::Identity() * (-J * p);
}

// Snow plasticity (Stomakhin et al. 2013, Sec. 5, eq. 9-11): clamp the singular values of the
// trial elastic F into [1 - theta_c, 1 + theta_s]; the plastic part takes the rest, so
// Jp <- Jp det(Sigma_trial) / det(Sigma_clamped). Returns the new elastic F.
template <int D>
Mat<D> snow_project(const Mat<D>& F, const Material& m, Scalar& Jp, Svd<D>& s) {
  s = svd(F);
  const Scalar before = s.sigma.prod();
  for (int k = 0; k < D; ++k) s.sigma(k) = std::clamp(s.sigma(k), 1 - m.theta_c, 1 + m.theta_s);
  Jp *= before / s.sigma.prod();
  return s.U * s.sigma.asDiagonal() * s.V.transpose();
}

// The same projection in 2D without U and V: F splits into a rotation-like and a
// reflection-like part, F = [[e, -f], [f, e]] + [[g, k], [k, -g]] with e = (F00 + F11) / 2,
// f = (F10 - F01) / 2, g = (F00 - F11) / 2, k = (F01 + F10) / 2, whose norms r1 = |(e, f)| and
// r2 = |(g, k)| give the signed singular values sigma = r1 + r2, r1 - r2 (the convention of
// svd above: the second is negative for a reflection), and U diag(s1, s2) V^T keeps this form
// with r1 -> (s1 + s2) / 2 and r2 -> (s1 - s2) / 2. Clamping the singular values therefore only
// rescales the two parts: two square roots, no eigenvectors, and F is returned bit for bit when
// nothing clamps. A part of zero norm has an undefined direction; its new norm is then zero too
// (r2 = 0: s1 = s2 clamp alike) or it is taken as the identity (r1 = 0, as svd above).
inline Mat<2> snow_project(const Mat<2>& F, const Material& m, Scalar& Jp) {
  const Scalar e = 0.5 * (F(0, 0) + F(1, 1)), f = 0.5 * (F(1, 0) - F(0, 1));
  const Scalar g = 0.5 * (F(0, 0) - F(1, 1)), k = 0.5 * (F(0, 1) + F(1, 0));
  const Scalar r1 = std::sqrt(e * e + f * f), r2 = std::sqrt(g * g + k * k);
  const Scalar s1 = r1 + r2, s2 = r1 - r2;
  const Scalar lo = 1 - m.theta_c, hi = 1 + m.theta_s;
  const Scalar c1 = std::clamp(s1, lo, hi), c2 = std::clamp(s2, lo, hi);
  if (c1 == s1 && c2 == s2) return F;
  Jp *= (s1 * s2) / (c1 * c2);
  const Scalar n1 = 0.5 * (c1 + c2), n2 = 0.5 * (c1 - c2);
  const Scalar a1 = r1 > 0 ? n1 / r1 : 0, a2 = r2 > 0 ? n2 / r2 : 0;
  const Scalar E = r1 > 0 ? a1 * e : n1, Fs = a1 * f, G = a2 * g, K = a2 * k;
  Mat<2> out;
  out << E + G, K - Fs, Fs + K, E - G;
  return out;
}

// Drucker-Prager return mapping in log-strain space (Klar et al. 2016, Sec. 7.3, Algorithm 2):
// with eps = log(Sigma), its deviator eps^ and the trace measured from the apex,
//   tr > 0 (tension beyond the apex)   -> eps = apex_trace / d (projection onto the tip),
//   dg = |eps^| + (d lambda + 2 mu) / (2 mu) tr alpha <= 0 -> inside the cone: no change,
//   otherwise                           eps <- eps - dg eps^ / |eps^| (onto the cone).
// Jp accumulates the plastic volume change. Returns the new elastic F.
//
// The mu(I) law (m.friction_law == MuI; Jop, Forterre and Pouliquen 2006) in the same space:
// the Hencky stress has deviator 2 mu eps^ and Kirchhoff pressure -(d lambda + 2 mu) tr / d, so
// Jop's ratio |tau| / p = mu_f, |tau| = sqrt(tau':tau' / 2), is the cone
// |eps^| = c mu_f with c = -sqrt(2) / d (d lambda + 2 mu) / (2 mu) tr (the constant law's
// alpha = sqrt(2) mu_f / d). A step whose trial deviator q = |eps^| lies outside the static
// cone (q > c mu_s) flows plastically by dq, i.e. at the shear rate gamma_dot = sqrt(2) dq / dt
// (simple shear at rate gamma_dot moves |eps^| by gamma_dot dt / sqrt(2)), with the inertial
// number I = gamma_dot d_g / sqrt(p / rho_s) = beta dq (p the Cauchy pressure), and lands on the
// cone of mu(I): q - dq = c (mu_s + (mu_2 - mu_s) beta dq / (I0 + beta dq)). Times (I0 + beta dq)
// this is the quadratic beta dq^2 - b dq - a0 I0 = 0, b = a0 beta - I0 - c (mu_2 - mu_s) beta,
// a0 = q - c mu_s > 0, whose one positive root is taken (in the form without cancellation).
template <int D>
Mat<D> sand_project(const Mat<D>& F, const Material& m, Scalar& Jp, Svd<D>& s, Scalar dt) {
  s = svd(F);
  Vec<D> eps = s.sigma.array().abs().max(1e-12).log().matrix();
  const Scalar tr = eps.sum() - m.apex_trace;
  const Vec<D> dev = eps - Vec<D>::Constant(eps.sum() / D);
  const Scalar dev_norm = dev.norm();
  const Scalar k = (D * m.lambda + 2 * m.mu) / (2 * m.mu);
  Vec<D> projected = eps;
  if (tr >= 0) {
    projected.setConstant(m.apex_trace / D);
  } else if (m.friction_law == Material::FrictionLaw::Constant) {
    const Scalar dg = dev_norm + k * tr * m.alpha;
    if (dg > 0 && dev_norm > 0) projected = eps - (dg / dev_norm) * dev;
  } else {
    const Scalar c = -std::sqrt(2.0) / D * k * tr;
    const Scalar a0 = dev_norm - c * m.mu_s;
    if (a0 > 0 && dev_norm > 0) {
      const Scalar dmu = m.mu_2 - m.mu_s;
      // Cauchy pressure from the Kirchhoff one, tau = J sigma.
      const Scalar p = -(D * m.lambda + 2 * m.mu) * eps.sum() / D / std::exp(eps.sum());
      Scalar dq;
      if (!(p > 0)) {  // no confinement (cohesive tension): I is infinite, mu = mu_2
        dq = std::max(a0 - c * dmu, 0.0);
      } else {
        const Scalar beta = std::sqrt(2.0) * m.grain_diameter / (dt * std::sqrt(p / m.grain_density));
        const Scalar I0 = m.inertial_number0;
        const Scalar b = a0 * beta - I0 - c * dmu * beta, root = std::sqrt(b * b + 4 * beta * a0 * I0);
        dq = b >= 0 ? (b + root) / (2 * beta) : 2 * a0 * I0 / (root - b);
      }
      projected = eps - (std::min(dq, dev_norm) / dev_norm) * dev;
    }
  }
  if (projected == eps) return F;
  Jp *= std::exp(eps.sum() - projected.sum());
  s.sigma = projected.array().exp().matrix();
  return s.U * s.sigma.asDiagonal() * s.V.transpose();
}

}  // namespace kinema::mpm
