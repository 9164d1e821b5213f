// The fast per-contact PSD projection (barrier.h, project_psd_translation_free: tridiagonal QL
// for the eigenvalues, inverse iteration for the negative ones' vectors) against the full
// eigendecomposition it replaces, on matrices with chosen spectra (repeated, clustered and
// zero eigenvalues) and on the barrier Hessians of every pair kind near contact; and the
// structural properties of the result (positive semidefinite, nearest: H - P is the negative
// part, orthogonal to P). The broad phase's exact box-pair descents (Bvh::query_box_pairs /
// query_box_self, before and after a refit) and BroadPhase::find against the brute-force pair
// sets, on random boxes and on degenerate ones: coincident, zero-extent (points, flat boxes),
// far apart, touching, many equal coordinates.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <random>
#include <set>

#include "contact/barrier.h"
#include "contact/collision.h"
#include "geometry/bvh.h"

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

// constraint_barrier's clamp (which forms a point-point term's clamp as its rank-one matrix and
// projects an edge pair reduced to a point-edge formula, mollifier inactive, on those three
// vertices) against the reference: the full eigendecomposition of the same term's unprojected
// Hessian over its whole stencil. Energy and gradient unchanged by the projection (bitwise).
// Tolerance as check_projection (both backward stable, 1e-12 ~ 4500 eps of |H|).
TEST(ContactProjection, ConstraintClampEqualsReferenceOnEveryReducedKind) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<Scalar> u(-1, 1), w(0.05, 0.95);
  const Scalar dhat = 0.05, dhat2 = dhat * dhat;
  Model model;  // no planes: constraint_barrier reads nothing else of it
  int seen[6][2] = {};
  auto check = [&](const Constraint& c, const std::vector<Scalar>& x) {
    Vec<12> g, g_clamped;
    Mat<12> H, clamped;
    const Scalar e = constraint_barrier(model, c, x.data(), dhat2, &g, &H, Projection::None);
    if (!(e > 0)) return;
    const Scalar e_clamped = constraint_barrier(model, c, x.data(), dhat2, &g_clamped, &clamped, Projection::Clamp);
    Mat<12> reference = H;
    const int k = c.stencil_size();
    if (k == 4) project_psd_translation_free_reference<4>(reference);
    if (k == 3) project_psd_translation_free_reference<3>(reference);
    if (k == 2) project_psd_translation_free_reference<2>(reference);
    const Scalar scale = H.norm();
    EXPECT_EQ(e_clamped, e);
    EXPECT_EQ((g_clamped - g).norm(), 0);
    EXPECT_LE((clamped - reference).norm(), 1e-12 * scale) << static_cast<int>(c.kind) << " stencil " << k;
    const Eigen::SelfAdjointEigenSolver<Mat<12>> eig(clamped);
    EXPECT_GE(eig.eigenvalues().minCoeff(), -1e-12 * scale);
    ++seen[static_cast<int>(c.kind)][c.eps_x > 0];
  };
  for (int trial = 0; trial < 400; ++trial) {
    const Scalar h = dhat * w(rng);
    // A point over a triangle's face, edge or corner.
    const Vec3 t0(0, 0, 0), t1(1, 0.2 * u(rng), 0.1 * u(rng)), t2(0.3 * u(rng), 1, 0.1 * u(rng));
    const Vec3 n = (t1 - t0).cross(t2 - t0).normalized();
    const Vec3 over[3] = {Vec3(0.3, 0.3, 0) + 0.1 * Vec3(u(rng), u(rng), 0), 0.5 * (t0 + t1) - Vec3(0, 0.01, 0),
                          t0 - 0.01 * Vec3(1, 1, 0)};
    const Vec3 p = over[trial % 3] + h * n;
    std::vector<Scalar> x = {p.x(), p.y(), p.z(), t0.x(), t0.y(), t0.z(), t1.x(), t1.y(), t1.z(), t2.x(), t2.y(), t2.z()};
    const Reduced r = point_triangle_region(p, t0, t1, t2);
    Constraint c;
    c.kind = r.kind;
    c.v = {-1, -1, -1, -1};
    for (int a = 0; a < vertex_count(r.kind); ++a) c.v[static_cast<size_t>(a)] = r.slot[a];
    check(c, x);
    // Two edges crossing (edge-edge), one ending over the other's middle (point-edge) or over
    // its end (point-point); nearly parallel (the mollifier active) on every fourth trial.
    const Vec3 a0(-0.5, 0.1 * u(rng), 0), a1(0.5, 0.1 * u(rng), 0);
    const Vec3 dir = trial % 4 == 0 ? Vec3(Vec3(1, 0.01 * u(rng), 0.01 * u(rng)).normalized())
                                    : Vec3(Vec3(0.3 * u(rng), 1, 0.5 + 0.3 * u(rng)).normalized());
    Vec3 b0, b1;
    const int where = (trial / 4) % 3;
    if (where == 0) {
      b0 = Vec3(0.1 * u(rng), 0.5 * (a0.y() + a1.y()), h) - 0.5 * dir, b1 = b0 + dir;
    } else {
      const Vec3 base = where == 1 ? Vec3(Vec3(0.2 * u(rng), 0, 0) + 0.5 * (a0 + a1)) : Vec3(a1 + Vec3(0.01, 0.01, 0));
      const Vec3 away = trial % 4 == 0 ? Vec3(Vec3(1, 0.01 * u(rng), 0.01 * u(rng)).normalized())
                                       : Vec3(Vec3(0.3 * u(rng), 0.5, 1).normalized());
      b0 = base + Vec3(0, 0, h), b1 = b0 + 0.8 * away;
    }
    x = {a0.x(), a0.y(), a0.z(), a1.x(), a1.y(), a1.z(), b0.x(), b0.y(), b0.z(), b1.x(), b1.y(), b1.z()};
    const Reduced q = edge_edge_region(a0, a1, b0, b1);
    Constraint ce;
    ce.kind = q.kind;
    ce.v = {-1, -1, -1, -1};
    for (int a = 0; a < vertex_count(q.kind); ++a) ce.v[static_cast<size_t>(a)] = q.slot[a];
    ce.edges = {0, 1, 2, 3};
    ce.eps_x = edge_mollifier_threshold(1, 1);
    check(ce, x);
  }
  // Every reduced kind was met, from point-face pairs and from edge pairs.
  EXPECT_GT(seen[static_cast<int>(PairKind::PT)][0], 20);
  EXPECT_GT(seen[static_cast<int>(PairKind::PE)][0], 20);
  EXPECT_GT(seen[static_cast<int>(PairKind::PP)][0], 20);
  EXPECT_GT(seen[static_cast<int>(PairKind::EE)][1], 20);
  EXPECT_GT(seen[static_cast<int>(PairKind::PE)][1], 20);
  EXPECT_GT(seen[static_cast<int>(PairKind::PP)][1], 5);
}

using Boxes = std::vector<Scalar>;
using PairSet = std::set<std::pair<Index, Index>>;

bool boxes_meet(const Boxes& lo, const Boxes& hi, size_t i, const Boxes& lo2, const Boxes& hi2, size_t j) {
  for (int a = 0; a < 3; ++a)
    if (!(lo[3 * i + a] <= hi2[3 * j + a] && lo2[3 * j + a] <= hi[3 * i + a])) return false;
  return true;
}

// Both exact descents against brute force: every overlapping pair exactly once, nothing else.
void expect_exact_pairs(const Boxes& alo, const Boxes& ahi, const Boxes& blo, const Boxes& bhi,
                        const geometry::Bvh& A, const geometry::Bvh& B, const char* what) {
  const size_t na = alo.size() / 3, nb = blo.size() / 3;
  PairSet pairs, self, want_pairs, want_self;
  size_t pair_visits = 0, self_visits = 0;
  A.query_box_pairs(B, [&](Index i, Index j) {
    ++pair_visits;
    pairs.insert({i, j});
  });
  A.query_box_self([&](Index i, Index j) {
    ++self_visits;
    EXPECT_NE(i, j) << what;
    self.insert({std::min(i, j), std::max(i, j)});
  });
  for (size_t i = 0; i < na; ++i) {
    for (size_t j = 0; j < nb; ++j)
      if (boxes_meet(alo, ahi, i, blo, bhi, j)) want_pairs.insert({static_cast<Index>(i), static_cast<Index>(j)});
    for (size_t j = i + 1; j < na; ++j)
      if (boxes_meet(alo, ahi, i, alo, ahi, j)) want_self.insert({static_cast<Index>(i), static_cast<Index>(j)});
  }
  EXPECT_EQ(pair_visits, pairs.size()) << what;  // no pair twice
  EXPECT_EQ(self_visits, self.size()) << what;
  EXPECT_EQ(pairs, want_pairs) << what;
  EXPECT_EQ(self, want_self) << what;
}

void expect_exact_pairs(const Boxes& alo, const Boxes& ahi, const Boxes& blo, const Boxes& bhi, const char* what) {
  expect_exact_pairs(alo, ahi, blo, bhi, geometry::Bvh(alo, ahi), geometry::Bvh(blo, bhi), what);
}

TEST(BroadPhase, ExactBoxPairDescentsEqualBruteForce) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<Scalar> u(0, 1);
  auto random_boxes = [&](size_t n, Scalar size, Boxes& lo, Boxes& hi) {
    lo.resize(3 * n);
    hi.resize(3 * n);
    for (size_t i = 0; i < lo.size(); ++i) {
      lo[i] = u(rng);
      hi[i] = lo[i] + size * u(rng);
    }
  };
  Boxes alo, ahi, blo, bhi;
  random_boxes(300, 0.15, alo, ahi);
  random_boxes(200, 0.15, blo, bhi);
  expect_exact_pairs(alo, ahi, blo, bhi, "random");
  {
    // Refit to other boxes of the same primitives: the kept leaf boxes follow.
    geometry::Bvh A(alo, ahi), B(blo, bhi);
    Boxes alo2, ahi2, blo2, bhi2;
    random_boxes(300, 0.3, alo2, ahi2);
    random_boxes(200, 0.05, blo2, bhi2);
    A.refit(alo2, ahi2);
    B.refit(blo2, bhi2);
    expect_exact_pairs(alo2, ahi2, blo2, bhi2, A, B, "refit");
  }
  // Coincident: every box the same (one SAH bin; median splits).
  alo.assign(3 * 40, 0.25);
  ahi.assign(3 * 40, 0.5);
  blo.assign(3 * 30, 0.25);
  bhi.assign(3 * 30, 0.5);
  expect_exact_pairs(alo, ahi, blo, bhi, "coincident");
  // Zero extent: points, some at the same place, against flat boxes (zero extent in one axis)
  // that they touch exactly.
  alo.clear();
  for (int i = 0; i < 60; ++i)
    for (int a = 0; a < 3; ++a) alo.push_back(Scalar((i * (a + 2)) % 5) / 4);
  ahi = alo;
  blo.clear();
  bhi.clear();
  for (int i = 0; i < 50; ++i) {
    const int flat = i % 3;
    for (int a = 0; a < 3; ++a) {
      const Scalar c = Scalar((i * (a + 1)) % 5) / 4;
      blo.push_back(c);
      bhi.push_back(a == flat ? c : c + 0.25);
    }
  }
  expect_exact_pairs(alo, ahi, blo, bhi, "points and flat boxes");
  // Many equal coordinates: unit cells of a grid (neighbours touch at faces, edges, corners).
  alo.clear();
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j)
      for (int k = 0; k < 4; ++k) alo.insert(alo.end(), {Scalar(i), Scalar(j), Scalar(k)});
  ahi = alo;
  for (Scalar& v : ahi) v += 1;
  blo = alo;
  bhi = ahi;
  for (Scalar& v : blo) v += 0.5;
  for (Scalar& v : bhi) v += 0.5;
  expect_exact_pairs(alo, ahi, blo, bhi, "grid");
  // Far apart: two clusters 1e6 apart, no pair across.
  random_boxes(100, 0.2, alo, ahi);
  random_boxes(100, 0.2, blo, bhi);
  for (size_t i = 0; i < blo.size(); ++i) blo[i] += 1e6, bhi[i] += 1e6;
  expect_exact_pairs(alo, ahi, blo, bhi, "far apart");
  // One primitive, and an empty tree.
  expect_exact_pairs(Boxes{0, 0, 0}, Boxes{1, 1, 1}, Boxes{1, 1, 1}, Boxes{2, 2, 2}, "single");
  expect_exact_pairs(Boxes{0, 0, 0}, Boxes{1, 1, 1}, Boxes{}, Boxes{}, "empty");
}

// A model of triangles only (no springs or tets needed by the broad phase).
Model surface_model(const std::vector<Scalar>& x, const std::vector<Index>& faces, const std::vector<char>& fixed) {
  Model m;
  m.vertex_count = static_cast<Index>(x.size() / 3);
  m.rest = x;
  m.fixed = fixed;
  m.driven.assign(fixed.size(), 0);
  m.faces = faces;
  std::set<std::pair<Index, Index>> edges;
  for (size_t f = 0; f < faces.size(); f += 3)
    for (int k = 0; k < 3; ++k) {
      const Index a = faces[f + k], b = faces[f + (k + 1) % 3];
      edges.insert({std::min(a, b), std::max(a, b)});
    }
  for (const auto& [a, b] : edges) m.edges.insert(m.edges.end(), {a, b});
  std::set<Index> used(faces.begin(), faces.end());
  m.points.assign(used.begin(), used.end());
  return m;
}

// BroadPhase::find against the brute-force pair sets of its definition (collision.h): every
// non-adjacent (point, face) and (edge, edge) pair, not all fixed, whose boxes swept over
// x -> x + dx and grown by r / 2 each meet; in lexicographic order, the same on a kept
// (refit) broad phase as on a fresh one.
size_t expect_find_equals_brute_force(const Model& m, const std::vector<Scalar>& x, const Scalar* dx, Scalar r,
                                      BroadPhase& kept, const char* what) {
  auto box = [&](std::initializer_list<Index> vs, Scalar* lo, Scalar* hi) {
    for (int c = 0; c < 3; ++c) {
      lo[c] = geometry::kInfinity;
      hi[c] = -geometry::kInfinity;
      for (Index v : vs) {
        const Scalar y = x[static_cast<size_t>(3 * v + c)];
        const Scalar z = dx ? y + dx[static_cast<size_t>(3 * v + c)] : y;
        lo[c] = std::min({lo[c], y, z});
        hi[c] = std::max({hi[c], y, z});
      }
      lo[c] -= r / 2;
      hi[c] += r / 2;
    }
  };
  auto meet = [](const Scalar* lo, const Scalar* hi, const Scalar* lo2, const Scalar* hi2) {
    for (int c = 0; c < 3; ++c)
      if (!(lo[c] <= hi2[c] && lo2[c] <= hi[c])) return false;
    return true;
  };
  auto fixed = [&](Index v) { return m.fixed[static_cast<size_t>(v)] != 0; };
  std::vector<std::array<Index, 2>> want_pf, want_ee;
  const Index nf = static_cast<Index>(m.faces.size() / 3), ne = static_cast<Index>(m.edges.size() / 2);
  for (Index p : m.points)
    for (Index f = 0; f < nf; ++f) {
      const Index* t = &m.faces[static_cast<size_t>(3 * f)];
      if (p == t[0] || p == t[1] || p == t[2]) continue;
      if (fixed(p) && fixed(t[0]) && fixed(t[1]) && fixed(t[2])) continue;
      Scalar lo[3], hi[3], lo2[3], hi2[3];
      box({p}, lo, hi);
      box({t[0], t[1], t[2]}, lo2, hi2);
      if (meet(lo, hi, lo2, hi2)) want_pf.push_back({p, f});
    }
  for (Index e = 0; e < ne; ++e)
    for (Index g = e + 1; g < ne; ++g) {
      const Index* a = &m.edges[static_cast<size_t>(2 * e)];
      const Index* b = &m.edges[static_cast<size_t>(2 * g)];
      if (a[0] == b[0] || a[0] == b[1] || a[1] == b[0] || a[1] == b[1]) continue;
      const bool fa = fixed(a[0]) && fixed(a[1]), fb = fixed(b[0]) && fixed(b[1]);
      if (fa && fb) continue;
      Scalar lo[3], hi[3], lo2[3], hi2[3];
      box({a[0], a[1]}, lo, hi);
      box({b[0], b[1]}, lo2, hi2);
      if (!meet(lo, hi, lo2, hi2)) continue;
      // A moving edge against a fixed one comes moving edge first.
      if (fa)
        want_ee.push_back({g, e});
      else
        want_ee.push_back({e, g});
    }
  std::sort(want_pf.begin(), want_pf.end());
  std::sort(want_ee.begin(), want_ee.end());
  Candidates fresh_out, kept_out;
  BroadPhase fresh;
  fresh.find(m, x.data(), dx, r, fresh_out);
  kept.find(m, x.data(), dx, r, kept_out);
  EXPECT_EQ(fresh_out.point_face, want_pf) << what;
  EXPECT_EQ(fresh_out.edge_edge, want_ee) << what;
  EXPECT_EQ(kept_out.point_face, want_pf) << what;
  EXPECT_EQ(kept_out.edge_edge, want_ee) << what;
  return want_pf.size() + want_ee.size();
}

TEST(BroadPhase, FindEqualsBruteForceOnDegenerateMeshes) {
  // A moving n x n grid of triangles (flat: zero extent along z, many equal coordinates) over a
  // fixed copy of itself; then the moving grid coincident with the fixed one, collapsed to
  // zero-area triangles, far apart, and swept through it.
  const int n = 6;
  std::vector<Scalar> x;
  std::vector<Index> faces;
  for (int copy = 0; copy < 2; ++copy) {
    const Index base = static_cast<Index>(x.size() / 3);
    for (int i = 0; i <= n; ++i)
      for (int j = 0; j <= n; ++j) x.insert(x.end(), {Scalar(i) / n, Scalar(j) / n, copy ? Scalar(0) : Scalar(0.05)});
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        const Index a = base + i * (n + 1) + j, b = a + 1, c = a + (n + 1), d = c + 1;
        faces.insert(faces.end(), {a, b, d, a, d, c});
      }
  }
  const Index half = static_cast<Index>(x.size() / 6);
  std::vector<char> fixed(x.size() / 3, 0);
  for (Index v = half; v < 2 * half; ++v) fixed[static_cast<size_t>(v)] = 1;
  const Model m = surface_model(x, faces, fixed);
  BroadPhase kept;
  expect_find_equals_brute_force(m, x, nullptr, 0.01, kept, "grid above grid");
  EXPECT_GT(expect_find_equals_brute_force(m, x, nullptr, 0.2, kept, "grid above grid, wide"), 500u);
  std::vector<Scalar> y = x;
  for (Index v = 0; v < half; ++v) y[static_cast<size_t>(3 * v + 2)] = 0;
  expect_find_equals_brute_force(m, y, nullptr, 0, kept, "coincident grids, r = 0");
  EXPECT_GT(expect_find_equals_brute_force(m, y, nullptr, 1e-3, kept, "coincident grids"), 500u);
  for (Index v = 0; v < half; ++v)
    for (int c = 0; c < 3; ++c) y[static_cast<size_t>(3 * v + c)] = Scalar(0.5);
  EXPECT_GT(expect_find_equals_brute_force(m, y, nullptr, 1e-3, kept, "collapsed to a point"), 500u);
  y = x;
  for (Index v = 0; v < half; ++v) y[static_cast<size_t>(3 * v)] += 1e6;
  expect_find_equals_brute_force(m, y, nullptr, 1e-3, kept, "far apart");
  std::vector<Scalar> dx(x.size(), 0);
  for (Index v = 0; v < half; ++v) dx[static_cast<size_t>(3 * v + 2)] = -0.1 - 0.01 * Scalar(v % 3);
  EXPECT_GT(expect_find_equals_brute_force(m, x, dx.data(), 0, kept, "swept through"), 500u);
  expect_find_equals_brute_force(m, x, nullptr, 0.01, kept, "back at the start");
}

}  // namespace
}  // namespace kinema::contact

namespace kinema::contact {
namespace {

// find_constraints against brute force: every non-adjacent point-face and edge-edge pair (not
// all fixed) whose region formula's squared distance is below dhat2, with that distance, in
// the same order; through the one-shot path (broad phase at dhat, no box prefilter, the
// plane / line bound first) and from candidates of a wider sweep (box prefilter). Two n x n
// grids, the upper one moving, a fraction of dhat above the lower one, jittered so that
// points sit over faces, edges and corners, and edges cross at every angle; then tilted
// so that many edges are nearly parallel (the bound abstains there).
TEST(ContactNarrowPhase, FindConstraintsEqualsBruteForce) {
  const int n = 5;
  const Scalar dhat = 0.02, dhat2 = dhat * dhat;
  std::mt19937 rng(23);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  std::vector<Index> faces;
  for (int copy = 0; copy < 2; ++copy) {
    const Index base = copy * (n + 1) * (n + 1);
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        const Index a = base + i * (n + 1) + j, b = a + 1, c = a + (n + 1), d = c + 1;
        faces.insert(faces.end(), {a, b, d, a, d, c});
      }
  }
  for (int trial = 0; trial < 6; ++trial) {
    std::vector<Scalar> x;
    const Scalar tilt = trial % 2 ? 0.002 : 0.3;
    for (int copy = 0; copy < 2; ++copy)
      for (int i = 0; i <= n; ++i)
        for (int j = 0; j <= n; ++j) {
          const Scalar jitter = copy ? 0.3 / n : 0.05 / n;
          const Scalar px = Scalar(i) / n + jitter * u(rng) + (copy ? 0.37 / n : 0);
          const Scalar py = Scalar(j) / n + jitter * u(rng) + (copy ? 0.21 / n : 0);
          const Scalar pz = copy ? dhat * (0.2 + 0.6 * (u(rng) + 1) / 2) + tilt * dhat * (px - 0.5) : 0;
          x.insert(x.end(), {px, py, pz});
        }
    std::vector<char> fixed(x.size() / 3, 0);
    for (size_t v = 0; v < fixed.size() / 2; ++v) fixed[v] = 1;
    const Model m = surface_model(x, faces, fixed);
    struct Want { PairKind kind; Scalar d; };
    std::vector<Want> want;
    auto fixed_all = [&](std::initializer_list<Index> vs) {
      for (Index v : vs)
        if (!fixed[static_cast<size_t>(v)]) return false;
      return true;
    };
    auto P = [&](Index v) { return Vec3(x[3 * v], x[3 * v + 1], x[3 * v + 2]); };
    auto keep = [&](const Reduced& r, const Vec3* y) {
      Vec3 v[4];
      for (int k = 0; k < vertex_count(r.kind); ++k) v[k] = y[r.slot[k]];
      const Scalar d = reduced_distance(r.kind, v);
      if (d < dhat2) want.push_back({r.kind, d});
    };
    const Index nf = static_cast<Index>(faces.size() / 3), ne = static_cast<Index>(m.edges.size() / 2);
    for (Index p : m.points)
      for (Index f = 0; f < nf; ++f) {
        const Index* t = &faces[static_cast<size_t>(3 * f)];
        if (p == t[0] || p == t[1] || p == t[2] || fixed_all({p, t[0], t[1], t[2]})) continue;
        const Vec3 y[4] = {P(p), P(t[0]), P(t[1]), P(t[2])};
        keep(point_triangle_region(y[0], y[1], y[2], y[3]), y);
      }
    for (Index e = 0; e < ne; ++e)
      for (Index g = e + 1; g < ne; ++g) {
        const Index* a = &m.edges[static_cast<size_t>(2 * e)];
        const Index* b = &m.edges[static_cast<size_t>(2 * g)];
        if (a[0] == b[0] || a[0] == b[1] || a[1] == b[0] || a[1] == b[1] || fixed_all({a[0], a[1], b[0], b[1]})) continue;
        // The moving edge first, as the broad phase orders a moving-fixed pair.
        const bool swap = fixed_all({a[0], a[1]});
        const Index* first = swap ? b : a;
        const Index* second = swap ? a : b;
        const Vec3 y[4] = {P(first[0]), P(first[1]), P(second[0]), P(second[1])};
        keep(edge_edge_region(y[0], y[1], y[2], y[3]), y);
      }
    BroadPhase broad;
    const std::vector<Constraint> one_shot = find_constraints(m, broad, x.data(), dhat2);
    Candidates wide;
    broad.find(m, x.data(), nullptr, 3 * dhat, wide);
    const std::vector<Constraint> from_wide = find_constraints(m, wide, x.data(), dhat2);
    ASSERT_GT(want.size(), 50u) << trial;
    for (const auto* got : {&one_shot, &from_wide}) {
      // The same multiset of (kind, distance): the order within the point-face block follows
      // the broad phase's pair order, which the brute-force loops above reproduce only up to
      // the moving-edge-first swap, so compare sorted.
      ASSERT_EQ(got->size(), want.size()) << trial;
      std::vector<std::pair<int, Scalar>> a, b;
      for (const Constraint& c : *got) a.push_back({static_cast<int>(c.kind), c.d});
      for (const Want& w : want) b.push_back({static_cast<int>(w.kind), w.d});
      std::sort(a.begin(), a.end());
      std::sort(b.begin(), b.end());
      EXPECT_EQ(a, b) << trial;
    }
    // Both paths give the same constraints in the same order.
    ASSERT_EQ(one_shot.size(), from_wide.size());
    for (size_t k = 0; k < one_shot.size(); ++k) {
      EXPECT_EQ(one_shot[k].v, from_wide[k].v);
      EXPECT_EQ(one_shot[k].d, from_wide[k].d);
    }
  }
}

}  // namespace
}  // namespace kinema::contact
