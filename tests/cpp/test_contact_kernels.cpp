// The fast per-contact PSD projection (barrier.h, project_psd_translation_free: tridiagonal QL
// for the eigenvalues, inverse iteration for the negative ones' vectors) against the full
// eigendecomposition it replaces, on matrices with chosen spectra (repeated, clustered and
// zero eigenvalues) and on the barrier Hessians of every pair kind near contact; and the
// structural properties of the result (positive semidefinite, nearest: H - P is the negative
// part, orthogonal to P).
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <random>

#include "contact/barrier.h"

namespace kinema::contact {
namespace {

// Q = B^T (x) I3: an orthonormal basis of the complement of the translations of K vertices.
template <int K>
Eigen::Matrix<Scalar, 3 * K, 3 * (K - 1)> translation_free_q() {
  const auto B = translation_free_basis<K>();
  Eigen::Matrix<Scalar, 3 * K, 3 * (K - 1)> Q;
  for (int a = 0; a < K; ++a)
    for (int b = 0; b < K - 1; ++b) Q.template block<3, 3>(3 * a, 3 * b) = B(b, a) * Mat3::Identity();
  return Q;
}

// H = Q V diag(lambda) V^T Q^T with V a random rotation: a translation-free Hessian with the
// given spectrum on the complement.
template <int K, class Rng>
Mat<12> with_spectrum(const Vec<3 * (K - 1)>& lambda, Rng& rng) {
  constexpr int R = 3 * (K - 1);
  std::normal_distribution<Scalar> g(0, 1);
  Mat<R> M;
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < R; ++j) M(i, j) = g(rng);
  const Eigen::HouseholderQR<Mat<R>> qr(M);
  const Mat<R> V = qr.householderQ();
  const auto Q = translation_free_q<K>();
  Mat<12> H = Mat<12>::Zero();
  H.template topLeftCorner<3 * K, 3 * K>() = Q * (V * lambda.asDiagonal() * V.transpose()) * Q.transpose();
  return H;
}

// Both projections, their relative Frobenius difference, and the properties of the fast one.
// Tolerances: both are backward stable eigen-solvers (each eigenpair exact for a matrix within
// c N eps |H| of H, N <= 9, c a small constant), so they agree to a few hundred eps relative:
// 1e-12 is 4500 eps; PSD and complementarity to the same bound.
template <int K>
void check_projection(const Mat<12>& H, const char* what) {
  constexpr int n = 3 * K;
  Mat<12> fast = H, reference = H;
  project_psd_translation_free<K>(fast);
  project_psd_translation_free_reference<K>(reference);
  const Scalar scale = H.norm();
  ASSERT_GT(scale, 0) << what;
  EXPECT_LE((fast - reference).norm(), 1e-12 * scale) << what;
  const Mat<n> P = fast.template topLeftCorner<n, n>(), N = P - H.template topLeftCorner<n, n>();
  const Eigen::SelfAdjointEigenSolver<Mat<n>> eig_p(P), eig_n(N);
  EXPECT_GE(eig_p.eigenvalues().minCoeff(), -1e-12 * scale) << what;  // P is PSD
  EXPECT_GE(eig_n.eigenvalues().minCoeff(), -1e-12 * scale) << what;  // P - H = -(negative part) is PSD
  EXPECT_LE((P * N).norm(), 1e-12 * scale * scale) << what;           // P and the removed part are orthogonal
  EXPECT_LE((fast - fast.transpose()).norm(), 1e-14 * scale) << what;
  EXPECT_TRUE(fast.bottomRows(12 - n).isZero(0) && fast.rightCols(12 - n).isZero(0)) << what;
}

TEST(ContactProjection, FastClampEqualsFullEigendecompositionOnChosenSpectra) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  for (int trial = 0; trial < 200; ++trial) {
    // Spectra spanning 12 decades with 1 .. 4 negative eigenvalues, zeros, and (every third
    // trial) negative eigenvalues repeated exactly: the inverse iteration's cluster case.
    Vec<9> l;
    const int negatives = 1 + trial % 4;
    for (int i = 0; i < 9; ++i) l[i] = std::pow(10.0, 6 * u(rng));
    for (int i = 0; i < negatives; ++i) l[i] = -l[i];
    if (trial % 3 == 0) l[1] = l[0];
    if (trial % 5 == 0) l[8] = l[7] = 0;
    check_projection<4>(with_spectrum<4>(l, rng), "K = 4");
    Vec<6> l6 = l.head<6>();
    check_projection<3>(with_spectrum<3>(l6, rng), "K = 3");
    Vec<3> l3 = l.head<3>();
    check_projection<2>(with_spectrum<2>(l3, rng), "K = 2");
  }
  // Nothing negative: unchanged. Everything negative: zero.
  Vec<9> pos = Vec<9>::LinSpaced(1, 9), neg = -pos;
  Mat<12> H = with_spectrum<4>(pos, rng), P = H;
  project_psd_translation_free<4>(P);
  EXPECT_EQ((P - H).norm(), 0);
  H = with_spectrum<4>(neg, rng);
  project_psd_translation_free<4>(H);
  EXPECT_LE(H.norm(), 1e-13 * 9);
}

TEST(ContactProjection, FastClampEqualsFullEigendecompositionOnBarrierHessians) {
  // Every pair kind a few percent to 95 % of dhat from contact, on random shapes: the exact
  // Hessian is indefinite (about two negative eigenvalues) with exact zeros (in-plane motions).
  std::mt19937 rng(13);
  std::uniform_real_distribution<Scalar> u(-1, 1), w(0.02, 0.95);
  const Scalar dhat = 0.05, dhat2 = dhat * dhat;
  int indefinite = 0;
  for (int trial = 0; trial < 300; ++trial) {
    const Vec3 t0(0, 0, 0), t1(1, 0.2 * u(rng), 0.1 * u(rng)), t2(0.3 * u(rng), 1, 0.1 * u(rng));
    const Scalar h = dhat * w(rng);
    Vec3 y[4];
    Mat<12> H;
    Vec<12> g;
    // Point over the face (PT), over an edge (PE), over a corner (PP).
    const Vec3 n = (t1 - t0).cross(t2 - t0).normalized();
    const Vec3 over[3] = {Vec3(0.3, 0.3, 0) + 0.1 * Vec3(u(rng), u(rng), 0), 0.5 * (t0 + t1) - Vec3(0, 0.01, 0),
                          t0 - 0.01 * Vec3(1, 1, 0)};
    for (int region = 0; region < 3; ++region) {
      y[0] = over[region] + h * n, y[1] = t0, y[2] = t1, y[3] = t2;
      Scalar d;
      const Reduced r = point_triangle_region(y[0], y[1], y[2], y[3], &d);
      if (!(d < dhat2)) continue;
      const int k = vertex_count(r.kind);
      Vec3 v[4];
      for (int a = 0; a < k; ++a) v[a] = y[r.slot[a]];
      const Reduced own{r.kind, {0, 1, 2, 3}};
      pair_barrier(own, v, 0, dhat2, &g, &H);
      Mat<12> unclamped = H;
      project_psd_translation_free_reference<4>(unclamped);
      indefinite += (unclamped - H).norm() > 0;
      if (k == 4) check_projection<4>(H, "pt");
      if (k == 3) check_projection<3>(H, "pe");
      if (k == 2) check_projection<2>(H, "pp");
    }
    // Two crossing edges at distance h, rest lengths such that the mollifier is active on
    // every other trial (nearly parallel edges).
    const Scalar tilt = trial % 2 ? 1.0 : 0.01;
    y[0] = Vec3(-0.5, 0.1 * u(rng), 0), y[1] = Vec3(0.5, 0.1 * u(rng), 0);
    y[2] = Vec3(0.1 * u(rng), -0.5 * tilt, h) + Vec3(-0.5, 0, 0) * (1 - tilt);
    y[3] = Vec3(0.1 * u(rng), 0.5 * tilt, h) + Vec3(0.5, 0, 0) * (1 - tilt);
    const Reduced r = edge_edge_region(y[0], y[1], y[2], y[3]);
    const Scalar eps_x = edge_mollifier_threshold(1, 1);
    if (pair_barrier(r, y, eps_x, dhat2, &g, &H) > 0) check_projection<4>(H, "ee");
  }
  EXPECT_GT(indefinite, 300);  // the clamp had work to do on most of the ~1000 Hessians
}

}  // namespace
}  // namespace kinema::contact
