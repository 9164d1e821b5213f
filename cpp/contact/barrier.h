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

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>

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

// The orthonormal rows of B (K - 1 x K), orthogonal to (1, ..., 1): a Hadamard basis (K = 4,
// 2) or Helmert's (K = 3). Q = B^T (x) I3 (3K x 3(K - 1)) is an orthonormal basis of the
// complement of the rigid translations of K vertices.
template <int K>
inline Eigen::Matrix<Scalar, K - 1, K> translation_free_basis() {
  Eigen::Matrix<Scalar, K - 1, K> B;
  if constexpr (K == 4) {
    B << 1, 1, -1, -1, 1, -1, 1, -1, 1, -1, -1, 1;
    B *= 0.5;
  } else if constexpr (K == 3) {
    B << 1 / std::sqrt(2.0), -1 / std::sqrt(2.0), 0, 1 / std::sqrt(6.0), 1 / std::sqrt(6.0), -2 / std::sqrt(6.0);
  } else {
    B << 1 / std::sqrt(2.0), -1 / std::sqrt(2.0);
  }
  return B;
}

// Q^T H Q over the leading 3K x 3K block: sums of 3x3 blocks weighted by B's entries.
template <int K>
inline Mat<3 * (K - 1)> restrict_translation_free(const Mat<12>& H, const Eigen::Matrix<Scalar, K - 1, K>& B) {
  constexpr int R = 3 * (K - 1);
  if constexpr (K == 4) {
    // B's rows are the Hadamard rows (1, 1, -1, -1) / 2, (1, -1, 1, -1) / 2, (1, -1, -1, 1) / 2:
    // by butterflies, sums and differences of blocks (the same sums as below, fewer products).
    (void)B;
    auto rows = [](const Mat3& h0, const Mat3& h1, const Mat3& h2, const Mat3& h3, Mat3* out) {
      const Mat3 s01 = h0 + h1, d01 = h0 - h1, s23 = h2 + h3, d23 = h2 - h3;
      out[0] = 0.5 * (s01 - s23);
      out[1] = 0.5 * (d01 + d23);
      out[2] = 0.5 * (d01 - d23);
    };
    Mat3 T[3][4];  // T[b][c] = sum_a B(b, a) H(a, c)
    for (int c = 0; c < 4; ++c) {
      Mat3 out[3];
      rows(H.block<3, 3>(0, 3 * c), H.block<3, 3>(3, 3 * c), H.block<3, 3>(6, 3 * c), H.block<3, 3>(9, 3 * c), out);
      for (int b = 0; b < 3; ++b) T[b][c] = out[b];
    }
    Mat<R> Ar;
    for (int b = 0; b < 3; ++b) {
      Mat3 out[3];
      rows(T[b][0], T[b][1], T[b][2], T[b][3], out);
      for (int d = 0; d < 3; ++d) Ar.template block<3, 3>(3 * b, 3 * d) = out[d];
    }
    return Ar;
  }
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
  return Ar;
}

// Reference of project_psd_translation_free (below): the nearest positive semidefinite matrix
// of the leading 3K x 3K block by a full eigendecomposition (Eigen's) of Q^T H Q, then
// Q P Q^T. A barrier term is invariant under translating all its K vertices, so its Hessian
// vanishes on translations: H = Q (Q^T H Q) Q^T exactly, and projecting the smaller Q^T H Q
// gives the same matrix (9 x 9 instead of 12 x 12 eigenproblems). The rest of H is zero.
template <int K>
inline void project_psd_translation_free_reference(Mat<12>& H) {
  constexpr int R = 3 * (K - 1);
  const Eigen::Matrix<Scalar, K - 1, K> B = translation_free_basis<K>();
  const Mat<R> Ar = restrict_translation_free<K>(H, B);
  Eigen::SelfAdjointEigenSolver<Mat<R>> eig(Ar);
  if (eig.eigenvalues().minCoeff() >= 0) return;
  const Eigen::Matrix<Scalar, R, R> V = eig.eigenvectors();
  const Mat<R> P = V * eig.eigenvalues().cwiseMax(Scalar(0)).asDiagonal() * V.transpose();
  Eigen::Matrix<Scalar, R, 3 * K> T;
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

namespace detail {

// A small symmetric eigenproblem in the textbook way (Golub & Van Loan, "Matrix
// Computations", 4th ed., sec. 8.3 and 8.2.2), sized at compile time so that every loop is
// unrolled: Householder reduction to a tridiagonal T = Q^T A Q, its eigenvalues by implicit QL
// with Wilkinson shifts (no eigenvectors accumulated), then the eigenvectors of the few
// eigenvalues wanted by inverse iteration on T (O(N) per solve) carried back through the
// reflectors.
template <int N>
struct Tridiagonal {
  Scalar d[N], e[N];  // diagonal; e[i] couples i and i + 1 (e[N - 1] = 0)
  Scalar v[N][N];     // v[k]: unit reflector k, acting on indices k + 1 .. N - 1
  bool reflect[N];
};

template <int N>
inline void tridiagonalize(Eigen::Matrix<Scalar, N, N> A, Tridiagonal<N>& t) {
  for (int k = 0; k < N - 2; ++k) {
    t.d[k] = A(k, k);
    Scalar tail = 0;
    for (int i = k + 2; i < N; ++i) tail += A(i, k) * A(i, k);
    const Scalar x0 = A(k + 1, k);
    t.reflect[k] = tail > 0;
    if (!t.reflect[k]) {
      t.e[k] = x0;
      std::fill(t.v[k], t.v[k] + N, Scalar(0));  // never read (reflect[k]); GCC cannot tell
      continue;
    }
    // v = x - alpha e_1 (alpha = -sign(x0) |x|, no cancellation), normalised: (I - 2 v v^T) x = alpha e_1.
    const Scalar norm = std::sqrt(x0 * x0 + tail);
    const Scalar alpha = x0 > 0 ? -norm : norm;
    Scalar* v = t.v[k];
    v[k + 1] = x0 - alpha;
    for (int i = k + 2; i < N; ++i) v[i] = A(i, k);
    const Scalar inv = 1 / std::sqrt(v[k + 1] * v[k + 1] + tail);
    for (int i = k + 1; i < N; ++i) v[i] *= inv;
    t.e[k] = alpha;
    // A22 <- H A22 H = A22 - 2 (v u^T + u v^T), with w = A22 v and u = w - (v . w) v.
    Scalar w[N], c = 0;
    for (int i = k + 1; i < N; ++i) {
      Scalar s = 0;
      for (int j = k + 1; j < N; ++j) s += A(j, i) * v[j];  // A symmetric: down column i
      w[i] = s;
      c += v[i] * s;
    }
    for (int i = k + 1; i < N; ++i) w[i] -= c * v[i];
    for (int j = k + 1; j < N; ++j)
      for (int i = k + 1; i < N; ++i) A(i, j) -= 2 * (v[i] * w[j] + w[i] * v[j]);
  }
  t.d[N - 2] = A(N - 2, N - 2);
  t.d[N - 1] = A(N - 1, N - 1);
  t.e[N - 2] = A(N - 1, N - 2);
  t.e[N - 1] = 0;
}

// Eigenvalues (unsorted, in d) of the tridiagonal (d, e) by implicit QL with Wilkinson shifts;
// e is destroyed. An off-diagonal entry below eps |T| is dropped (absolute accuracy: each
// eigenvalue moves by less than eps |T|; a relative test would chase the exactly zero
// eigenvalues barrier Hessians have down to the denormal range). False when an eigenvalue has
// not converged in 60 sweeps.
template <int N>
inline bool tridiagonal_eigenvalues(Scalar* d, Scalar* e) {
  constexpr Scalar eps = std::numeric_limits<Scalar>::epsilon();
  Scalar norm = 0;
  for (int i = 0; i < N; ++i) norm = std::max(norm, std::abs(d[i]) + std::abs(e[i]) + (i > 0 ? std::abs(e[i - 1]) : 0));
  const Scalar tol = eps * norm;
  for (int l = 0; l < N; ++l) {
    for (int iter = 0;; ++iter) {
      int m = l;
      for (; m < N - 1; ++m)
        if (std::abs(e[m]) <= tol) break;
      if (m == l) break;
      if (iter == 60) return false;
      Scalar g = (d[l + 1] - d[l]) / (2 * e[l]);
      Scalar r = std::sqrt(g * g + 1);
      g = d[m] - d[l] + e[l] / (g + (g < 0 ? -r : r));
      Scalar s = 1, c = 1, p = 0;
      bool split = false;
      for (int i = m - 1; i >= l; --i) {
        const Scalar f = s * e[i], b = c * e[i];
        r = std::sqrt(f * f + g * g);
        e[i + 1] = r;
        if (r == 0) {
          d[i + 1] -= p;
          e[m] = 0;
          split = true;
          break;
        }
        const Scalar inv = 1 / r;
        s = f * inv;
        c = g * inv;
        g = d[i + 1] - p;
        r = (d[i] - g) * s + 2 * c * b;
        p = s * r;
        d[i + 1] = g + p;
        g = c * r - b;
      }
      if (split) continue;
      d[l] -= p;
      e[l] = g;
      e[m] = 0;
    }
  }
  return true;
}

// T - lambda I factored by Gaussian elimination with partial pivoting (the factor has two
// superdiagonals), for solves x <- (T - lambda I)^{-1} x; a pivot that vanishes is replaced by
// `tiny` (inverse iteration wants the near-singular solve: its growth is the point).
template <int N>
struct ShiftedTridiagonalLu {
  Scalar u0[N], u1[N], u2[N], l[N], inv_u0[N];  // inv_u0: the pivots' reciprocals (no division in solve)
  bool swap[N];

  ShiftedTridiagonalLu(const Tridiagonal<N>& t, Scalar lambda, Scalar tiny) {
    Scalar a = t.d[0] - lambda, b = t.e[0], c = 0;  // the current row at columns i, i + 1, i + 2
    for (int i = 0; i < N - 1; ++i) {
      const Scalar n0 = t.e[i], n1 = t.d[i + 1] - lambda, n2 = i + 2 < N ? t.e[i + 1] : Scalar(0);
      swap[i] = std::abs(n0) > std::abs(a);
      if (!swap[i]) {
        if (a == 0) a = tiny;
        l[i] = n0 / a;
        u0[i] = a, u1[i] = b, u2[i] = c;
        a = n1 - l[i] * b, b = n2 - l[i] * c;
      } else {
        l[i] = a / n0;
        u0[i] = n0, u1[i] = n1, u2[i] = n2;
        a = b - l[i] * n1, b = c - l[i] * n2;
      }
      c = 0;
    }
    u0[N - 1] = a == 0 ? tiny : a;
    for (int i = 0; i < N; ++i) inv_u0[i] = 1 / u0[i];
  }

  void solve(Scalar* x) const {
    for (int i = 0; i < N - 1; ++i) {
      if (swap[i]) std::swap(x[i], x[i + 1]);
      x[i + 1] -= l[i] * x[i];
    }
    for (int i = N - 1; i >= 0; --i) {
      Scalar s = x[i];
      if (i + 1 < N) s -= u1[i] * x[i + 1];
      if (i + 2 < N) s -= u2[i] * x[i + 2];
      x[i] = s * inv_u0[i];
    }
  }
};

// The nearest positive semidefinite matrix of the symmetric A (N x N) as A minus its negative
// part: sum over the eigenpairs with lambda < 0 of lambda z z^T, returned as (lambda_k, z_k),
// k < count. False when the iteration does not certify its result (the caller falls back to a
// full eigendecomposition).
template <int N>
inline bool negative_eigenpairs(const Eigen::Matrix<Scalar, N, N>& A, Scalar* lambda, Scalar (*z)[N], int& count) {
  count = 0;
  const Scalar scale = A.cwiseAbs().maxCoeff();
  if (!(scale > 0)) return scale == 0;  // zero: nothing negative; NaN: refuse
  if (!std::isfinite(scale)) return false;
  Tridiagonal<N> t;
  tridiagonalize<N>(A * (1 / scale), t);
  Scalar d[N], e[N];
  for (int i = 0; i < N; ++i) d[i] = t.d[i], e[i] = t.e[i];
  if (!tridiagonal_eigenvalues<N>(d, e)) return false;
  // Eigenvalues of the scaled matrix are O(1), each known to about N eps: those below -N eps are
  // negative beyond rounding; clamping the others would change A by less than its rounding.
  constexpr Scalar eps = std::numeric_limits<Scalar>::epsilon();
  Scalar norm = 0;
  for (int i = 0; i < N; ++i) norm = std::max(norm, std::abs(d[i]));
  for (int i = 0; i < N; ++i)
    if (d[i] < -N * eps * norm) lambda[count++] = d[i];
  if (count == 0) return true;
  std::sort(lambda, lambda + count);
  const Scalar tiny = eps * std::max(norm, Scalar(1e-300));
  static constexpr Scalar start[7] = {1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6};  // 1 + 0.1 j
  for (int k = 0; k < count; ++k) {
    Scalar* x = z[k];
    // A start with no special symmetry, then inverse iterations (each orthogonalised against
    // the vectors already found for eigenvalues within 1e-3 |T|, a cluster) until x is an
    // eigenvector to working accuracy, |T x - lambda x| within rounding of |T| (two
    // iterations: lambda is exact to rounding); not within three, the caller falls back.
    for (int i = 0; i < N; ++i) x[i] = start[(5 * i + 3 * k) % 7];
    const ShiftedTridiagonalLu<N> lu(t, lambda[k], tiny);
    bool certified = false;
    for (int it = 0; it < 3 && !certified; ++it) {
      lu.solve(x);
      for (int j = 0; j < k; ++j) {
        if (lambda[k] - lambda[j] > 1e-3 * norm) continue;
        Scalar dot = 0;
        for (int i = 0; i < N; ++i) dot += x[i] * z[j][i];
        for (int i = 0; i < N; ++i) x[i] -= dot * z[j][i];
      }
      Scalar n2 = 0;
      for (int i = 0; i < N; ++i) n2 += x[i] * x[i];
      if (!(n2 > 0) || !std::isfinite(n2)) return false;
      const Scalar inv = 1 / std::sqrt(n2);
      for (int i = 0; i < N; ++i) x[i] *= inv;
      Scalar res = 0;
      for (int i = 0; i < N; ++i) {
        Scalar r = (t.d[i] - lambda[k]) * x[i];
        if (i > 0) r += t.e[i - 1] * x[i - 1];
        if (i + 1 < N) r += t.e[i] * x[i + 1];
        res = std::max(res, std::abs(r));
      }
      certified = it > 0 && res <= 4 * N * eps * std::max(norm, Scalar(1));
    }
    if (!certified) return false;
  }
  // Back through the reflectors (Q = H_0 H_1 ... H_{N-3}), and to A's scale.
  for (int k = 0; k < count; ++k) {
    Scalar* x = z[k];
    for (int r = N - 3; r >= 0; --r) {
      if (!t.reflect[r]) continue;
      Scalar dot = 0;
      for (int i = r + 1; i < N; ++i) dot += t.v[r][i] * x[i];
      for (int i = r + 1; i < N; ++i) x[i] -= 2 * dot * t.v[r][i];
    }
    lambda[k] *= scale;
  }
  return true;
}

}  // namespace detail

// Nearest positive semidefinite matrix of the leading 3K x 3K block (negative eigenvalues
// clamped to zero); the rest of H is zero. The term's Hessian vanishes on rigid translations
// of its K vertices, so its eigenproblem is that of the 3(K - 1) x 3(K - 1) restriction
// Q^T H Q (see project_psd_translation_free_reference); a barrier term's restriction has one
// or two negative eigenvalues, so rather than a full eigendecomposition H loses only its
// negative part: H <- H - sum_{lambda < 0} lambda (Q z)(Q z)^T, the eigenvalues by implicit QL
// on a tridiagonal reduction and their vectors by inverse iteration (detail:: above; a few
// microseconds less per pair than a full decomposition). Equal to the reference to rounding
// (tests/cpp/test_contact_kernels.cpp); a result the iteration cannot certify is recomputed by
// the reference.
template <int K>
inline void project_psd_translation_free(Mat<12>& H) {
  constexpr int R = 3 * (K - 1);
  const Eigen::Matrix<Scalar, K - 1, K> B = translation_free_basis<K>();
  const Mat<R> Ar = restrict_translation_free<K>(H, B);
  Scalar lambda[R], z[R][R];
  int count = 0;
  if (!detail::negative_eigenpairs<R>(Ar, lambda, z, count)) {
    project_psd_translation_free_reference<K>(H);
    return;
  }
  for (int k = 0; k < count; ++k) {
    // w = Q z: vertex a gets sum_b B(b, a) z_b.
    Vec<3 * K> w;
    for (int a = 0; a < K; ++a) {
      Vec3 s = Vec3::Zero();
      for (int b = 0; b < K - 1; ++b) s += B(b, a) * Eigen::Map<const Vec3>(z[k] + 3 * b);
      w.template segment<3>(3 * a) = s;
    }
    H.template topLeftCorner<3 * K, 3 * K>().noalias() -= lambda[k] * w * w.transpose();
  }
}

// The same for a Hessian that is zero but on the vertices slot[0..K) of a larger stencil (an
// edge pair whose distance reduced to a point-edge pair, its mollifier inactive): the
// projection of a matrix that is zero outside a block is the projection of that block, so the
// block is projected alone (a 6 x 6 eigenproblem instead of 9 x 9) and written back.
template <int K>
inline void project_psd_on_vertices(Mat<12>& H, const int* slot) {
  Mat<12> B = Mat<12>::Zero();
  for (int a = 0; a < K; ++a)
    for (int b = 0; b < K; ++b) B.block<3, 3>(3 * a, 3 * b) = H.block<3, 3>(3 * slot[a], 3 * slot[b]);
  project_psd_translation_free<K>(B);
  for (int a = 0; a < K; ++a)
    for (int b = 0; b < K; ++b) H.block<3, 3>(3 * slot[a], 3 * slot[b]) = B.block<3, 3>(3 * a, 3 * b);
}

}  // namespace kinema::contact
