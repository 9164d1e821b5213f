// SPH building blocks: the cell-grid neighbour search equals brute force (2D, 3D, clustered
// and duplicate points, every cell subdivision, queries off the grid), its AVX2 and baseline
// paths give identical lists, the Morton order is a permutation, and the cubic spline kernel is
// normalised with derivatives that match finite differences.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "core/errors.h"
#include "core/simd.h"
#include "particles/neighbor_grid.h"
#include "particles/neighbor_lists.h"
#include "sph/kernels.h"

namespace kinema {

namespace {

template <int D>
std::vector<Index> brute_pairs(const std::vector<Scalar>& x, Scalar r) {
  const Index n = static_cast<Index>(x.size()) / D;
  std::vector<Index> pairs;
  for (Index i = 0; i < n; ++i)
    for (Index j = i + 1; j < n; ++j) {
      Scalar d2 = 0;
      for (int a = 0; a < D; ++a) d2 += (x[j * D + a] - x[i * D + a]) * (x[j * D + a] - x[i * D + a]);
      if (d2 < r * r) {
        pairs.push_back(i);
        pairs.push_back(j);
      }
    }
  return pairs;
}

template <int D>
std::vector<Scalar> random_points(Index n, unsigned seed, bool clustered) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<Scalar> u(0, 1);
  std::vector<Scalar> x(static_cast<size_t>(n * D));
  for (Index i = 0; i < n; ++i)
    for (int a = 0; a < D; ++a)
      x[i * D + a] = clustered ? std::floor(u(rng) * 4) + 1e-3 * u(rng) : u(rng);
  // Exact duplicates of the first points.
  for (Index i = 0; i < n / 10; ++i)
    for (int a = 0; a < D; ++a) x[(n - 1 - i) * D + a] = x[i * D + a];
  return x;
}

}  // namespace

template <int D>
void expect_pairs_match(bool clustered) {
  for (Scalar r : {0.002, 0.05, 0.3}) {
    const auto x = random_points<D>(600, 7 + D, clustered);
    const auto got = neighbor_pairs<D>(x.data(), 600, r);
    EXPECT_EQ(got, brute_pairs<D>(x, r)) << "D=" << D << " r=" << r << " clustered=" << clustered;
  }
}

TEST(NeighborGrid, PairsEqualBruteForce2D) { expect_pairs_match<2>(false); expect_pairs_match<2>(true); }
TEST(NeighborGrid, PairsEqualBruteForce3D) { expect_pairs_match<3>(false); expect_pairs_match<3>(true); }

TEST(NeighborGrid, RejectsABadSubdivision) {
  const std::vector<Scalar> x = {0, 0, 1, 1};
  NeighborGrid<2> grid;
  EXPECT_THROW(grid.build(x.data(), 2, 0.5, 0), InvalidArgument);
  EXPECT_THROW(grid.build(x.data(), 2, 0.5, NeighborGrid<2>::kMaxSubdivision + 1), InvalidArgument);
}

TEST(NeighborGrid, CandidatesCoverTheRadiusForQueriesOutsideTheGrid) {
  std::vector<Scalar> x = {0, 0, 0.5, 0.5, 1, 1};
  NeighborGrid<2> grid;
  grid.build(x.data(), 3, 0.3);
  std::vector<Index> seen;
  grid.for_each_candidate(Eigen::Vector2d(-0.2, -0.1), [&](Index j) { seen.push_back(j); });
  EXPECT_NE(std::find(seen.begin(), seen.end(), 0), seen.end());
  seen.clear();
  grid.for_each_candidate(Eigen::Vector2d(5, 5), [&](Index j) { seen.push_back(j); });
  EXPECT_TRUE(seen.empty());
}

// NeighborLists::build against brute force, row by row: the same set of neighbours (the row
// order is the grid's cell order), for both paths, and the AVX2 rows equal the baseline rows
// entry for entry. Queries: the binned points themselves (self) and points scattered beyond
// the grid (not self).
template <int D>
void expect_lists_match(bool clustered, int subdivision) {
  const Index n = 700, nq = 300;
  const auto x = random_points<D>(n, 11 + D, clustered);
  std::vector<Scalar> q = random_points<D>(nq, 5, false);
  for (Scalar& c : q) c = 1.6 * c - 0.3;
  for (Scalar r : {0.002, 0.07, 0.3}) {
    NeighborGrid<D> grid;
    grid.build(x.data(), n, r, subdivision);
    for (bool self : {true, false}) {
      const std::vector<Scalar>& xq = self ? x : q;
      const Index m = self ? n : nq;
      NeighborLists base, wide;
      base.build<D>(grid, xq.data(), m, r, self, false);
      wide.build<D>(grid, xq.data(), m, r, self, true);
      if (cpu_has_avx2()) {
        EXPECT_EQ(base.start, wide.start) << "D=" << D << " r=" << r << " subdivision=" << subdivision;
        EXPECT_EQ(base.list, wide.list) << "D=" << D << " r=" << r << " subdivision=" << subdivision;
      }
      for (Index i = 0; i < m; ++i) {
        std::vector<std::int32_t> got(base.list.begin() + base.start[i], base.list.begin() + base.start[i + 1]);
        std::sort(got.begin(), got.end());
        std::vector<std::int32_t> want;
        for (Index j = 0; j < n; ++j) {
          Scalar d2 = 0;
          for (int a = 0; a < D; ++a) d2 += (x[j * D + a] - xq[i * D + a]) * (x[j * D + a] - xq[i * D + a]);
          if (d2 < r * r && !(self && j == i)) want.push_back(static_cast<std::int32_t>(j));
        }
        ASSERT_EQ(got, want) << "D=" << D << " r=" << r << " subdivision=" << subdivision << " self=" << self
                             << " query " << i << " clustered=" << clustered;
      }
    }
  }
}

TEST(NeighborLists, RowsEqualBruteForceAndAvx2EqualsBaseline2D) {
  for (int sub = 1; sub <= NeighborGrid<2>::kMaxSubdivision; ++sub) {
    expect_lists_match<2>(false, sub);
    expect_lists_match<2>(true, sub);
  }
}
TEST(NeighborLists, RowsEqualBruteForceAndAvx2EqualsBaseline3D) {
  for (int sub = 1; sub <= NeighborGrid<3>::kMaxSubdivision; ++sub) {
    expect_lists_match<3>(false, sub);
    expect_lists_match<3>(true, sub);
  }
}

TEST(NeighborGrid, FinerCellsOfferFewerCandidates) {
  // A jittered lattice of spacing 0.1 in the unit cube, radius r = 0.2. The cells that meet
  // the ball around a point fill on average the ball grown by a cell of edge c (Steiner):
  // c^3 + 6 c^2 r + 3 pi c r^2 + 4 pi r^3 / 3, that is 20.6 r^3 at c = r and 10.5 r^3 at
  // c = r / 2 (ratio 0.51; the cube's faces cut both alike).
  std::vector<Scalar> x;
  std::mt19937 rng(3);
  std::uniform_real_distribution<Scalar> jitter(-0.01, 0.01);
  for (int i = 0; i < 10; ++i)
    for (int j = 0; j < 10; ++j)
      for (int k = 0; k < 10; ++k)
        for (Scalar c : {0.1 * i, 0.1 * j, 0.1 * k}) x.push_back(c + jitter(rng));
  const Index n = static_cast<Index>(x.size()) / 3;
  Index candidates[2] = {0, 0};
  for (int sub : {1, 2}) {
    NeighborGrid<3> grid;
    grid.build(x.data(), n, 0.2, sub);
    EXPECT_EQ(grid.reach(), sub);
    for (Index i = 0; i < n; ++i)
      grid.for_each_candidate(Eigen::Map<const Eigen::Vector3d>(x.data() + 3 * i), 0.2,
                              [&](Index) { ++candidates[sub - 1]; });
  }
  EXPECT_LT(candidates[1], 0.6 * candidates[0]) << candidates[1] << " vs " << candidates[0];
}

TEST(NeighborGrid, MortonOrderIsAPermutation) {
  const auto x = random_points<3>(1000, 3, false);
  auto order = morton_order<3>(x.data(), 1000, 0.05);
  std::sort(order.begin(), order.end());
  for (Index k = 0; k < 1000; ++k) ASSERT_EQ(order[k], k);
}

TEST(Kernel, NormalisedIn2DAnd3D) {
  for (int d : {2, 3}) {
    const Scalar h = 0.7;
    const int steps = 100000;
    Scalar integral = 0;
    for (int k = 0; k < steps; ++k) {
      const Scalar r = (k + 0.5) * h / steps;  // midpoint rule
      const Scalar shell = d == 2 ? 2 * sph::kPi * r : 4 * sph::kPi * r * r;
      integral += shell * sph::kernel_w(r, h, d) * h / steps;
    }
    EXPECT_NEAR(integral, 1.0, 1e-8) << "d=" << d;
    EXPECT_EQ(sph::kernel_w(h, h, d), 0.0);
  }
}

TEST(Kernel, DerivativesMatchFiniteDifferencesAndGradient) {
  const Scalar h = 1.1, eps = 1e-6;
  for (int d : {2, 3})
    for (Scalar q = 0.02; q < 0.99; q += 0.037) {
      const Scalar r = q * h;
      const Scalar fd1 = (sph::kernel_w(r + eps, h, d) - sph::kernel_w(r - eps, h, d)) / (2 * eps);
      const Scalar fd2 = (sph::kernel_dw(r + eps, h, d) - sph::kernel_dw(r - eps, h, d)) / (2 * eps);
      EXPECT_NEAR(sph::kernel_dw(r, h, d), fd1, 1e-6) << "d=" << d << " q=" << q;
      EXPECT_NEAR(sph::kernel_d2w(r, h, d), fd2, 1e-5) << "d=" << d << " q=" << q;
    }
  const sph::CubicSpline<3> W(h);
  const Eigen::Vector3d xij(0.3, -0.2, 0.1);
  const Eigen::Vector3d g = W.grad(xij);
  EXPECT_NEAR(g.norm(), std::abs(sph::kernel_dw(xij.norm(), h, 3)), 1e-12);
  EXPECT_LT(g.dot(xij), 0);  // W decreases outward: the gradient points back to j
  EXPECT_NEAR(W.w(xij.norm()), sph::kernel_w(xij.norm(), h, 3), 1e-14);
  EXPECT_EQ(W.grad(Eigen::Vector3d::Zero()).norm(), 0.0);
}

}  // namespace kinema
