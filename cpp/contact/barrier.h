// The IPC log barrier and the smoothed Coulomb friction of Li et al., "Incremental Potential
// Contact", ACM TOG 39(4), 2020 (eq. 6 and section 5), on squared distances d and the squared
// activation distance dhat2 = dhat^2:
//   b(d) = -(d - dhat2)^2 ln(d / dhat2) for 0 < d < dhat2, 0 beyond     (C^2 at dhat2, +inf at 0)
// Edge-edge pairs carry the mollifier of Li et al. 2020 (sec. 4.1, "parallel edge-edge
// contact") on s = |(a1 - a0) x (b1 - b0)|^2, with eps_x = 1e-3 |a1 - a0|^2 |b1 - b0|^2 at rest:
//   m(s) = (2 - s / eps_x) s / eps_x for s < eps_x, else 1
// so the term m(s) b(d) vanishes with its gradient where the edges turn parallel, and the kink
// of the segment distance there (its closest points jump) no longer reaches the energy's
// gradient: the term is C^1 there (C^2 along lines through a parallel configuration).
// Friction of one contact, lagged normal force lambda and sliding displacement u (2D, in the
// contact's tangent plane) over a step h, with the relative tangential speed y = |u| / h:
//   D(u) = mu lambda h f0(y),  f0' = f1,  f1(y) = 2 y / eps_v - y^2 / eps_v^2 for y < eps_v, else 1
// so that -dD/du = -mu lambda f1(y) u / |u| is Coulomb's force smoothed below the speed eps_v
// (eq. 14-16). Its Hessian is positive semidefinite as written (eigenvalues mu lambda / h times
// f1'(y) along u and f1(y) / y across it), so no projection is needed.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <cmath>

#include "contact/distance.h"
#include "core/types.h"

namespace kinema::contact {

inline Scalar barrier(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  return -(d - dhat2) * (d - dhat2) * std::log(d / dhat2);
}

inline Scalar barrier_first(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  return (dhat2 - d) * (2 * std::log(d / dhat2) - dhat2 / d + 1);
}

inline Scalar barrier_second(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  const Scalar r = dhat2 / d;
  return -2 * std::log(d / dhat2) + r * r + 2 * r - 3;
}

inline Scalar edge_mollifier_threshold(Scalar rest_length_a2, Scalar rest_length_b2) {
  return 1e-3 * rest_length_a2 * rest_length_b2;
}

inline Scalar edge_mollifier(Scalar s, Scalar eps_x) {
  if (s >= eps_x) return 1;
  const Scalar r = s / eps_x;
  return (2 - r) * r;
}

inline Scalar edge_mollifier_first(Scalar s, Scalar eps_x) {
  if (s >= eps_x) return 0;
  return 2 * (1 - s / eps_x) / eps_x;
}

inline Scalar edge_mollifier_second(Scalar s, Scalar eps_x) {
  if (s >= eps_x) return 0;
  return -2 / (eps_x * eps_x);
}

// f0 with f0(0) = eps_v / 3 so that it is continuous with f0(y) = y at eps_v.
inline Scalar friction_f0(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return y;
  return -y * y * y / (3 * eps_v * eps_v) + y * y / eps_v + eps_v / 3;
}

// f1(y) / y, finite at y = 0.
inline Scalar friction_f1_over_y(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return 1 / y;
  return 2 / eps_v - y / (eps_v * eps_v);
}

// f1'(y), the stiffness along the sliding direction.
inline Scalar friction_f1_derivative(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return 0;
  return 2 / eps_v - 2 * y / (eps_v * eps_v);
}

// Rank-one (Gauss-Newton) positive semidefinite Hessian of a barrier term b(d(x)) with d = s^2
// the squared distance and s the distance: the exact Hessian is
//   H = b'' grad d grad d^T + b' Hess d = alpha grad s grad s^T + beta Hess s,
//   alpha = 4 d b'' + 2 b',  beta = 2 s b' <= 0,
// and R = max(alpha, 0) grad s grad s^T = max(b'' + b' / (2 d), 0) grad d grad d^T is the PSD
// projection of its first term. The projection P onto the PSD cone is 1-Lipschitz in the
// Frobenius norm, so |P(H) - R|_F <= |beta| |Hess s|_F: R differs from the eigen clamp P(H) by
// at most |beta| |Hess s|, relatively about s / (edge length) since alpha ~ 4 dhat^4 / d and
// |beta| ~ 2 dhat^4 / s for d << dhat^2 (Hess s ~ 1 / edge length). For a point-point pair
// (Hess s = (I - n n^T) / s, orthogonal to grad s) and a vertex-plane pair (Hess s = 0) R equals
// P(H) exactly. It needs no Hessian of d and no eigenproblem; a Newton matrix built from it
// keeps the exact gradient, so Newton converges to the same minimiser.
inline Scalar rank_one_barrier_weight(Scalar d, Scalar dhat2) {
  if (!(d < dhat2)) return 0;
  return std::max(barrier_second(d, dhat2) + barrier_first(d, dhat2) / (2 * d), Scalar(0));
}

// The barrier term of one pair, m(s) b(d), over its stencil y[0..4) (an edge pair: a0, a1, b0,
// b1; a point-triangle pair: the formula's own vertices): `r` is the distance formula and the
// stencil slots it reads; eps_x > 0 applies the edge mollifier. Gradient and Hessian (not
// projected) over the stencil, 3 entries per vertex, when g and H are given; zero beyond dhat2.
// rank_one: H is the rank-one PSD Hessian above instead where the mollifier is 1 (returns true
// then; false when H is the exact Hessian).
inline Scalar pair_barrier(const Reduced& r, const Vec3* y, Scalar eps_x, Scalar dhat2, Vec<12>* g, Mat<12>* H,
                           bool rank_one = false, bool* is_rank_one = nullptr) {
  if (is_rank_one) *is_rank_one = false;
  const int k = vertex_count(r.kind);
  Vec3 v[4];
  for (int a = 0; a < k; ++a) v[a] = y[r.slot[a]];
  const Scalar d = reduced_distance(r.kind, v);
  if (g) g->setZero();
  if (H) H->setZero();
  if (!(d < dhat2)) return 0;
  const Scalar b = barrier(d, dhat2);
  Scalar s = eps_x;
  Vec<12> gs;
  Mat<12> Hs;
  if (eps_x > 0) {
    s = (y[1] - y[0]).cross(y[3] - y[2]).squaredNorm();
    if (g && !(rank_one && H && !(s < eps_x))) s = ee_cross_derivatives(y[0], y[1], y[2], y[3], gs, H ? &Hs : nullptr);
  }
  const Scalar m = eps_x > 0 ? edge_mollifier(s, eps_x) : Scalar(1);
  if (!g) return m * b;
  if (rank_one && H && !(s < eps_x)) {
    // m = 1: g = b' grad d, H = w grad d grad d^T (no Hessian of d needed).
    Vec<12> gl;
    reduced_derivatives(r.kind, v, gl, nullptr);
    Vec<12> gd = Vec<12>::Zero();
    for (int a = 0; a < k; ++a) gd.segment<3>(3 * r.slot[a]) = gl.segment<3>(3 * a);
    *g = barrier_first(d, dhat2) * gd;
    *H = rank_one_barrier_weight(d, dhat2) * gd * gd.transpose();
    if (is_rank_one) *is_rank_one = true;
    return b;
  }
  Vec<12> gl;
  Mat<12> Hl;
  reduced_derivatives(r.kind, v, gl, H ? &Hl : nullptr);
  // The formula's derivatives, moved to the stencil slots it reads.
  Vec<12> gd = Vec<12>::Zero();
  Mat<12> Hd;
  if (H) Hd.setZero();
  for (int a = 0; a < k; ++a) {
    gd.segment<3>(3 * r.slot[a]) = gl.segment<3>(3 * a);
    if (H)
      for (int c = 0; c < k; ++c) Hd.block<3, 3>(3 * r.slot[a], 3 * r.slot[c]) = Hl.block<3, 3>(3 * a, 3 * c);
  }
  const Scalar b1 = barrier_first(d, dhat2), b2 = barrier_second(d, dhat2);
  *g = m * b1 * gd;
  if (H) *H = m * (b2 * gd * gd.transpose() + b1 * Hd);
  if (s < eps_x) {
    // Product rule on m(s(x)) b(d(x)).
    const Scalar m1 = edge_mollifier_first(s, eps_x), m2 = edge_mollifier_second(s, eps_x);
    *g += m1 * b * gs;
    if (H) {
      *H += (m2 * b) * gs * gs.transpose() + (m1 * b) * Hs;
      *H += (m1 * b1) * (gs * gd.transpose() + gd * gs.transpose());
    }
  }
  return m * b;
}

// Nearest positive semidefinite matrix of the leading 3K x 3K block (negative eigenvalues
// clamped to zero); the rest of H is zero. A barrier term is invariant under translating all
// its K vertices, so its Hessian vanishes on translations and lives on their orthogonal
// complement: with Q (3K x 3(K-1)) an orthonormal basis of that complement, H = Q (Q^T H Q) Q^T
// exactly, and projecting the smaller Q^T H Q gives the same matrix at about half the cost
// (9 x 9 instead of 12 x 12 eigenproblems); a Cholesky test first skips the eigenproblem when
// the restriction is already positive definite.
template <int K>
inline void project_psd_translation_free(Mat<12>& H) {
  constexpr int R = 3 * (K - 1);
  // Rows orthonormal and orthogonal to (1, ..., 1): a Hadamard basis (K = 4, 2) or Helmert's (K = 3).
  Eigen::Matrix<Scalar, K - 1, K> B;
  if constexpr (K == 4) {
    B << 1, 1, -1, -1, 1, -1, 1, -1, 1, -1, -1, 1;
    B *= 0.5;
  } else if constexpr (K == 3) {
    B << 1 / std::sqrt(2.0), -1 / std::sqrt(2.0), 0, 1 / std::sqrt(6.0), 1 / std::sqrt(6.0), -2 / std::sqrt(6.0);
  } else {
    B << 1 / std::sqrt(2.0), -1 / std::sqrt(2.0);
  }
  // Q = B^T (x) I3, so Q^T H Q and Q M Q^T are sums of 3x3 blocks weighted by B's entries.
  Eigen::Matrix<Scalar, R, 3 * K> T;
  for (int b = 0; b < K - 1; ++b)
    for (int c = 0; c < K; ++c) {
      Mat3 s = Mat3::Zero();
      for (int a = 0; a < K; ++a) s += B(b, a) * H.block<3, 3>(3 * a, 3 * c);
      T.template block<3, 3>(3 * b, 3 * c) = s;
    }
  Mat<R> Ar;
  for (int b = 0; b < K - 1; ++b)
    for (int d = 0; d < K - 1; ++d) {
      Mat3 s = Mat3::Zero();
      for (int c = 0; c < K; ++c) s += B(d, c) * T.template block<3, 3>(3 * b, 3 * c);
      Ar.template block<3, 3>(3 * b, 3 * d) = s;
    }
  // Positive definite already (a Cholesky factorisation exists): nothing to clamp.
  if (Eigen::LLT<Mat<R>>(Ar).info() == Eigen::Success) return;
  Eigen::SelfAdjointEigenSolver<Mat<R>> eig(Ar);
  if (eig.eigenvalues().minCoeff() >= 0) return;
  const Eigen::Matrix<Scalar, R, R> V = eig.eigenvectors();
  const Mat<R> P = V * eig.eigenvalues().cwiseMax(Scalar(0)).asDiagonal() * V.transpose();
  for (int b = 0; b < K - 1; ++b)
    for (int c = 0; c < K; ++c) {
      Mat3 s = Mat3::Zero();
      for (int d = 0; d < K - 1; ++d) s += B(d, c) * P.template block<3, 3>(3 * b, 3 * d);
      T.template block<3, 3>(3 * b, 3 * c) = s;
    }
  for (int a = 0; a < K; ++a)
    for (int c = 0; c < K; ++c) {
      Mat3 s = Mat3::Zero();
      for (int b = 0; b < K - 1; ++b) s += B(b, a) * T.template block<3, 3>(3 * b, 3 * c);
      H.block<3, 3>(3 * a, 3 * c) = s;
    }
}

}  // namespace kinema::contact
