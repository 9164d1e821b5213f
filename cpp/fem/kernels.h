// Per-element math of linear finite elements (triangles in 2D, tetrahedra in 3D) for isotropic
// hyperelastic energies psi(F): energy density, first Piola-Kirchhoff stress P = dpsi/dF, its
// derivative dP/dF (a d^2 x d^2 matrix acting on vec(F), column-major), and the element force
// and stiffness from F = Ds Dm^-1 (Sifakis & Barbic, "FEM simulation of 3D deformable solids",
// SIGGRAPH course notes 2012, sections 3-4 and 10).
//   linear:     psi = mu eps:eps + lam/2 tr(eps)^2,          eps = (F + F^T)/2 - I
//   stvk:       psi = mu E:E + lam/2 tr(E)^2,                E = (F^T F - I)/2
//   corotated:  psi = mu ||F - R||^2 + lam/2 (J - 1)^2       (fixed corotated, Stomakhin et al.
//               2012; F = R S by the rotation-variant SVD, defined for inverted F)
//   neohookean: psi = mu/2 (tr(F^T F) - d) + lam'/2 (J - alpha)^2 - mu^2 / (2 lam'), the stable
//               neo-Hookean of Smith, de Goes & Kim (ACM TOG 37, 2018), lam' = lam + mu and
//               alpha = 1 + mu/lam' so that it linearises to the given Lame parameters; it has no
//               log(J) and stays finite for J <= 0. The constant makes psi(rotation) = 0.
// The Hessian of the corotated term uses d(R)/dF = sum 2/(s_a + s_b) q_ab q_ab^T, the twist
// eigensystem of I_1 = tr(S) (Smith, de Goes & Kim, "Analytic eigensystems for isotropic
// distortion energies", ACM TOG 38, 2019, section 4).
// 2D elements are plane strain with unit thickness: F_33 = 1, so the 3D densities restricted to
// the plane are the formulas above with d = 2.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>

#include "core/types.h"

namespace kinema::fem {

enum class Material { Linear, StVK, Corotated, NeoHookean };

template <int D>
using Mat = Eigen::Matrix<Scalar, D, D>;
template <int D>
using HessF = Eigen::Matrix<Scalar, D * D, D * D>;  // acts on vec(F), index c*D + r
template <int D>
using ElementVec = Eigen::Matrix<Scalar, (D + 1) * D, 1>;
template <int D>
using ElementMat = Eigen::Matrix<Scalar, (D + 1) * D, (D + 1) * D, Eigen::RowMajor>;

// Lame parameters from Young's modulus E [Pa] and Poisson's ratio nu (3D relations, which
// plane strain keeps).
inline void lame(Scalar E, Scalar nu, Scalar& mu, Scalar& lam) {
  mu = E / (2 * (1 + nu));
  lam = E * nu / ((1 + nu) * (1 - 2 * nu));
}

template <int D>
Scalar det(const Mat<D>& F) { return F.determinant(); }

// dJ/dF, the cofactor matrix.
template <int D>
Mat<D> cofactor(const Mat<D>& F) {
  Mat<D> C;
  if constexpr (D == 2) {
    C << F(1, 1), -F(1, 0), -F(0, 1), F(0, 0);
  } else {
    C.col(0) = F.col(1).cross(F.col(2));
    C.col(1) = F.col(2).cross(F.col(0));
    C.col(2) = F.col(0).cross(F.col(1));
  }
  return C;
}

// J - 1 and cof(F) - I for F = I + H without cancellation (near the rest shape J - 1 and the
// energies are many orders of magnitude below their O(mu) terms, and the line search compares
// energies): det(I + H) - 1 = tr H + (tr(H)^2 - tr(H^2))/2 + det H, cof(I + H) - I =
// tr(H) I - H^T + cof(H) in 3D; tr H + det H and cof(H) in 2D.
template <int D>
Scalar det_minus_one(const Mat<D>& H) {
  if constexpr (D == 2) {
    return H.trace() + H.determinant();
  } else {
    const Scalar t = H.trace();
    return t + (t * t - (H * H).trace()) / 2 + H.determinant();
  }
}

template <int D>
Mat<D> cofactor_minus_identity(const Mat<D>& H) {
  if constexpr (D == 2) {
    return cofactor<D>(H);
  } else {
    return H.trace() * Mat<D>::Identity() - H.transpose() + cofactor<D>(H);
  }
}

// d^2 J / dF^2 on vec(F).
template <int D>
HessF<D> det_hessian(const Mat<D>& F) {
  HessF<D> H = HessF<D>::Zero();
  if constexpr (D == 2) {
    H(0, 3) = H(3, 0) = 1;
    H(1, 2) = H(2, 1) = -1;
  } else {
    auto hat = [](const Eigen::Matrix<Scalar, 3, 1>& a) {
      Mat<3> h;
      h << 0, -a(2), a(1), a(2), 0, -a(0), -a(1), a(0), 0;
      return h;
    };
    // d(f1 x f2)/df1 = -hat(f2), d(f1 x f2)/df2 = hat(f1), and cyclically.
    const Mat<3> h0 = hat(F.col(0)), h1 = hat(F.col(1)), h2 = hat(F.col(2));
    H.template block<3, 3>(0, 3) = -h2;
    H.template block<3, 3>(0, 6) = h1;
    H.template block<3, 3>(3, 0) = h2;
    H.template block<3, 3>(3, 6) = -h0;
    H.template block<3, 3>(6, 0) = -h1;
    H.template block<3, 3>(6, 3) = h0;
  }
  return H;
}

template <int D>
Eigen::Matrix<Scalar, D * D, 1> vec(const Mat<D>& A) {
  return Eigen::Map<const Eigen::Matrix<Scalar, D * D, 1>>(A.data());
}

// Rotation-variant SVD F = U diag(s) V^T with U, V rotations; s_D < 0 when F is inverted.
template <int D>
void rotation_svd(const Mat<D>& F, Mat<D>& U, Eigen::Matrix<Scalar, D, 1>& s, Mat<D>& V) {
  Eigen::JacobiSVD<Mat<D>> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  if (svd.info() != Eigen::Success) {
    // A non-finite F: Eigen returns without computing (its factors are left unset). NaN
    // singular values carry the non-finite state on to the solver's divergence check.
    U.setIdentity();
    V.setIdentity();
    s.setConstant(std::numeric_limits<Scalar>::quiet_NaN());
    return;
  }
  U = svd.matrixU();
  V = svd.matrixV();
  s = svd.singularValues();
  if (U.determinant() < 0) {
    U.col(D - 1) *= -1;
    s(D - 1) *= -1;
  }
  if (V.determinant() < 0) {
    V.col(D - 1) *= -1;
    s(D - 1) *= -1;
  }
}

// d^2 tr(S) / dF^2 = dR/dF on vec(F): twist modes q_ab = U T_ab V^T / sqrt(2) with
// eigenvalue 2 / (s_a + s_b) (Smith et al. 2019, eq. 33-36); the denominator is kept away
// from 0, where R is not differentiable (a degenerate, inverted element).
template <int D>
HessF<D> rotation_derivative(const Mat<D>& U, const Eigen::Matrix<Scalar, D, 1>& s,
                             const Mat<D>& V) {
  HessF<D> H = HessF<D>::Zero();
  for (int a = 0; a < D; ++a)
    for (int b = a + 1; b < D; ++b) {
      Mat<D> T = Mat<D>::Zero();
      T(a, b) = -1;
      T(b, a) = 1;
      const Mat<D> Q = U * T * V.transpose() / std::sqrt(Scalar(2));
      const auto q = vec<D>(Q);
      Scalar denom = s(a) + s(b);
      const Scalar floor = 1e-8 * std::max<Scalar>(1, s.cwiseAbs().maxCoeff());
      if (std::abs(denom) < floor) denom = denom < 0 ? -floor : floor;
      H.noalias() += (2 / denom) * q * q.transpose();
    }
  return H;
}

template <int D>
Scalar psi(const Mat<D>& F, Material m, Scalar mu, Scalar lam) {
  const Mat<D> I = Mat<D>::Identity();
  switch (m) {
    case Material::Linear: {
      const Mat<D> eps = (F + F.transpose()) / 2 - I;
      const Scalar tr = eps.trace();
      return mu * eps.squaredNorm() + lam / 2 * tr * tr;
    }
    case Material::StVK: {
      const Mat<D> H = F - I;
      const Mat<D> E = (H + H.transpose() + H.transpose() * H) / 2;
      const Scalar tr = E.trace();
      return mu * E.squaredNorm() + lam / 2 * tr * tr;
    }
    case Material::Corotated: {
      Mat<D> U, V;
      Eigen::Matrix<Scalar, D, 1> s;
      rotation_svd<D>(F, U, s, V);
      const Scalar J = s.prod();
      return mu * (s.array() - 1).square().sum() + lam / 2 * (J - 1) * (J - 1);
    }
    case Material::NeoHookean: {
      // = mu/2 (|F|^2 - d) + lam'/2 (J - alpha)^2 - mu^2/(2 lam') expanded about F = I:
      // mu/2 (|H|^2 + 2 tr H) + lam'/2 (J - 1)^2 - mu (J - 1), H = F - I.
      const Scalar l = lam + mu;
      const Mat<D> H = F - I;
      const Scalar Jm1 = det_minus_one<D>(H);
      return mu / 2 * (H.squaredNorm() + 2 * H.trace()) + l / 2 * Jm1 * Jm1 - mu * Jm1;
    }
  }
  return 0;
}

template <int D>
Mat<D> piola(const Mat<D>& F, Material m, Scalar mu, Scalar lam) {
  const Mat<D> I = Mat<D>::Identity();
  switch (m) {
    case Material::Linear: {
      const Mat<D> eps = (F + F.transpose()) / 2 - I;
      return 2 * mu * eps + lam * eps.trace() * I;
    }
    case Material::StVK: {
      const Mat<D> H = F - I;
      const Mat<D> E = (H + H.transpose() + H.transpose() * H) / 2;
      return F * (2 * mu * E + lam * E.trace() * I);
    }
    case Material::Corotated: {
      Mat<D> U, V;
      Eigen::Matrix<Scalar, D, 1> s;
      rotation_svd<D>(F, U, s, V);
      const Mat<D> R = U * V.transpose();
      return 2 * mu * (F - R) + lam * (s.prod() - 1) * cofactor<D>(F);
    }
    case Material::NeoHookean: {
      // mu F + lam' (J - alpha) cof F = mu (H - (cof F - I)) + lam' (J - 1) cof F
      const Scalar l = lam + mu;
      const Mat<D> H = F - I;
      return mu * (H - cofactor_minus_identity<D>(H)) + l * det_minus_one<D>(H) * cofactor<D>(F);
    }
  }
  return Mat<D>::Zero();
}

// P is linear in the Lame parameters for every model here: P = mu A(F) + lam B(F) (for the
// stable neo-Hookean through lam' = lam + mu and alpha = 1 + mu/lam', whose product
// lam' (J - alpha) = lam (J - 1) + mu (J - 1) - mu is linear too). Returns (A, B) = (dP/dmu,
// dP/dlam), the parameter derivatives of the adjoint step.
template <int D>
void piola_lame_derivatives(const Mat<D>& F, Material m, Mat<D>& A, Mat<D>& B) {
  const Mat<D> I = Mat<D>::Identity();
  switch (m) {
    case Material::Linear: {
      const Mat<D> eps = (F + F.transpose()) / 2 - I;
      A = 2 * eps;
      B = eps.trace() * I;
      return;
    }
    case Material::StVK: {
      const Mat<D> H = F - I;
      const Mat<D> E = (H + H.transpose() + H.transpose() * H) / 2;
      A = 2 * F * E;
      B = E.trace() * F;
      return;
    }
    case Material::Corotated: {
      Mat<D> U, V;
      Eigen::Matrix<Scalar, D, 1> s;
      rotation_svd<D>(F, U, s, V);
      A = 2 * (F - U * V.transpose());
      B = (s.prod() - 1) * cofactor<D>(F);
      return;
    }
    case Material::NeoHookean: {
      const Mat<D> H = F - I;
      B = det_minus_one<D>(H) * cofactor<D>(F);
      A = H - cofactor_minus_identity<D>(H) + B;
      return;
    }
  }
  A.setZero();  // unreachable (every Material returns above), as psi's and piola's 0
  B.setZero();
}

// dP/dF on vec(F) (symmetric: it is the Hessian of psi).
template <int D>
HessF<D> piola_derivative(const Mat<D>& F, Material m, Scalar mu, Scalar lam) {
  constexpr int N = D * D;
  const Mat<D> I = Mat<D>::Identity();
  HessF<D> H;
  switch (m) {
    case Material::Linear:
    case Material::StVK: {
      // Column by column: dP for the unit perturbation dF = e_r e_c^T.
      const Mat<D> E = (F.transpose() * F - I) / 2;
      const Mat<D> S = 2 * mu * E + lam * E.trace() * I;
      for (int c = 0; c < D; ++c)
        for (int r = 0; r < D; ++r) {
          Mat<D> dF = Mat<D>::Zero();
          dF(r, c) = 1;
          Mat<D> dP;
          if (m == Material::Linear) {
            dP = mu * (dF + dF.transpose()) + lam * dF.trace() * I;
          } else {
            const Mat<D> dE = (dF.transpose() * F + F.transpose() * dF) / 2;
            dP = dF * S + F * (2 * mu * dE + lam * dE.trace() * I);
          }
          H.col(c * D + r) = vec<D>(dP);
        }
      return H;
    }
    case Material::Corotated: {
      Mat<D> U, V;
      Eigen::Matrix<Scalar, D, 1> s;
      rotation_svd<D>(F, U, s, V);
      const auto g = vec<D>(cofactor<D>(F));
      H = 2 * mu * (HessF<D>::Identity() - rotation_derivative<D>(U, s, V));
      H.noalias() += lam * (g * g.transpose());
      H += lam * (s.prod() - 1) * det_hessian<D>(F);
      return H;
    }
    case Material::NeoHookean: {
      const Scalar l = lam + mu;
      const auto g = vec<D>(cofactor<D>(F));
      H = mu * HessF<D>::Identity();
      H.noalias() += l * (g * g.transpose());
      H += (l * det_minus_one<D>(F - I) - mu) * det_hessian<D>(F);  // lam' (J - alpha) d2J/dF2
      return H;
    }
  }
  (void)N;
  return HessF<D>::Zero();
}

// Definiteness fix: the nearest positive semidefinite matrix (negative eigenvalues clamped to
// 0). Applied to dP/dF, whose projection makes every element stiffness V B^T H B PSD. The
// eigen-decomposition runs only when a Cholesky attempt shows H is not already PD.
// Returns true when H was changed.
template <int D>
bool project_psd(HessF<D>& H) {
  if (Eigen::LLT<HessF<D>>(H).info() == Eigen::Success) return false;
  Eigen::SelfAdjointEigenSolver<HessF<D>> eig(H);
  const auto lambda = eig.eigenvalues().cwiseMax(Scalar(0));
  H = eig.eigenvectors() * lambda.asDiagonal() * eig.eigenvectors().transpose();
  return true;
}

// Rest-shape data of one element: Dm^-1 and the rest volume (area in 2D).
// Dm = [X1 - X0, ..., XD - X0]; returns the signed volume det(Dm)/d!.
template <int D>
Scalar rest_shape(const Scalar* X, const Index* elem, Mat<D>& Dm_inv) {
  Mat<D> Dm;
  for (int c = 0; c < D; ++c)
    for (int r = 0; r < D; ++r) Dm(r, c) = X[elem[c + 1] * D + r] - X[elem[0] * D + r];
  const Scalar vol = Dm.determinant() / (D == 2 ? 2 : 6);
  Dm_inv = Dm.inverse();
  return vol;
}

// F = Ds Dm^-1 with Ds = [x1 - x0, ..., xD - x0].
template <int D>
Mat<D> deformation_gradient(const Scalar* x, const Index* elem, const Mat<D>& Dm_inv) {
  Mat<D> Ds;
  for (int c = 0; c < D; ++c)
    for (int r = 0; r < D; ++r) Ds(r, c) = x[elem[c + 1] * D + r] - x[elem[0] * D + r];
  return Ds * Dm_inv;
}

// B = d vec(F) / d x_e, (D^2) x ((D+1) D): dF(r, c)/dx_a(s) = delta_rs b_a(c) with
// b_a = row a-1 of Dm^-1 (a >= 1) and b_0 = -sum of the others.
template <int D>
Eigen::Matrix<Scalar, D * D, (D + 1) * D> gradient_operator(const Mat<D>& Dm_inv) {
  Eigen::Matrix<Scalar, D * D, (D + 1) * D> B = Eigen::Matrix<Scalar, D * D, (D + 1) * D>::Zero();
  for (int a = 0; a <= D; ++a)
    for (int c = 0; c < D; ++c) {
      const Scalar b = a == 0 ? -Dm_inv.col(c).sum() : Dm_inv(a - 1, c);
      for (int s = 0; s < D; ++s) B(c * D + s, a * D + s) = b;
    }
  return B;
}

// Element gradient dW/dx_e of W = vol psi(F): vol P Dm^-T split over the vertices.
template <int D>
ElementVec<D> element_gradient(const Mat<D>& P, const Mat<D>& Dm_inv, Scalar vol) {
  const Mat<D> H = vol * P * Dm_inv.transpose();
  ElementVec<D> g;
  for (int r = 0; r < D; ++r) g(r) = -H.row(r).sum();
  for (int a = 1; a <= D; ++a)
    for (int r = 0; r < D; ++r) g(a * D + r) = H(r, a - 1);
  return g;
}

// Element stiffness d^2 W / dx_e^2 = vol B^T (dP/dF) B, using B's structure (D nonzeros per
// column, B(c D + s, a D + s) = b_a(c)): K_(a s)(b t) = vol sum_{c, c'} b_a(c) H_(c s)(c' t) b_b(c'),
// about 3x fewer operations than the dense triple product.
template <int D>
ElementMat<D> element_hessian(const HessF<D>& dPdF, const Mat<D>& Dm_inv, Scalar vol) {
  constexpr int K = (D + 1) * D;
  Eigen::Matrix<Scalar, D, D + 1> G;  // G(c, a) = b_a(c)
  for (int c = 0; c < D; ++c) {
    G(c, 0) = -Dm_inv.col(c).sum();
    for (int a = 1; a <= D; ++a) G(c, a) = Dm_inv(a - 1, c);
  }
  Eigen::Matrix<Scalar, D * D, K> HB;  // H B
  for (int i = 0; i < D * D; ++i)
    for (int b = 0; b <= D; ++b)
      for (int t = 0; t < D; ++t) {
        Scalar sum = 0;
        for (int c = 0; c < D; ++c) sum += dPdF(i, c * D + t) * G(c, b);
        HB(i, b * D + t) = sum;
      }
  ElementMat<D> Ke;
  for (int a = 0; a <= D; ++a)
    for (int s = 0; s < D; ++s)
      for (int j = 0; j < K; ++j) {
        Scalar sum = 0;
        for (int c = 0; c < D; ++c) sum += G(c, a) * HB(c * D + s, j);
        Ke(a * D + s, j) = vol * sum;
      }
  return Ke;
}

}  // namespace kinema::fem
