// The contact solver's 3x3-block Cholesky against a dense factorisation (solution to rounding,
// indefinite matrices refused), and the BVH's two-tree descents against brute force.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <random>
#include <set>
#include <utility>
#include <vector>

#include "contact/block_cholesky.h"
#include "core/simd.h"
#include "geometry/bvh.h"

namespace kinema::contact {

namespace {

// A symmetric matrix of 3x3 blocks on an nx x ny grid (each block row coupled to its grid
// neighbours and to a few random far blocks, which make fill), in the block CSR layout of
// NewtonSystem::view(), and the same as a dense matrix. `shift` is added to the diagonal.
struct BlockMatrix {
  std::vector<Index> row_ptr, col;
  std::vector<Scalar> values;
  Eigen::MatrixXd dense;
  CsrView view() const {
    const Index m = static_cast<Index>(row_ptr.size()) - 1;
    return {m, m, row_ptr.data(), col.data(), values.data()};
  }
};

BlockMatrix grid_matrix(int nx, int ny, Scalar shift, unsigned seed) {
  const int n = nx * ny;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  std::set<std::pair<int, int>> blocks;
  for (int i = 0; i < n; ++i) blocks.insert({i, i});
  auto couple = [&](int a, int b) {
    blocks.insert({a, b});
    blocks.insert({b, a});
  };
  for (int x = 0; x < nx; ++x)
    for (int y = 0; y < ny; ++y) {
      if (x + 1 < nx) couple(x * ny + y, (x + 1) * ny + y);
      if (y + 1 < ny) couple(x * ny + y, x * ny + y + 1);
    }
  std::uniform_int_distribution<int> pick(0, n - 1);
  for (int k = 0; k < n / 4; ++k) {
    const int a = pick(rng), b = pick(rng);
    if (a != b) couple(a, b);
  }
  BlockMatrix M;
  M.dense = Eigen::MatrixXd::Zero(3 * n, 3 * n);
  for (const auto& [i, j] : blocks) {
    if (j < i) continue;
    Eigen::Matrix3d B;
    for (int r = 0; r < 3; ++r)
      for (int s = 0; s < 3; ++s) B(r, s) = u(rng);
    if (i == j) B = (B * B.transpose()).eval();
    M.dense.block<3, 3>(3 * i, 3 * j) += B;
    if (i != j) M.dense.block<3, 3>(3 * j, 3 * i) += B.transpose();
  }
  // Diagonally dominant by blocks, then shifted.
  for (int i = 0; i < 3 * n; ++i) M.dense(i, i) += M.dense.row(i).cwiseAbs().sum() + shift;
  M.row_ptr.push_back(0);
  for (int i = 0; i < n; ++i) {
    std::vector<int> cols;
    for (const auto& [a, b] : blocks)
      if (a == i) cols.push_back(b);
    for (int r = 0; r < 3; ++r) {
      for (int b : cols)
        for (int s = 0; s < 3; ++s) {
          M.col.push_back(3 * b + s);
          M.values.push_back(M.dense(3 * i + r, 3 * b + s));
        }
      M.row_ptr.push_back(static_cast<Index>(M.col.size()));
    }
  }
  return M;
}

}  // namespace

TEST(BlockCholesky, SolvesLikeADenseFactorisation) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const BlockMatrix M = grid_matrix(7, 6, 0.0, seed);
    BlockCholesky chol;
    chol.analyze(M.view());
    ASSERT_TRUE(chol.factorize(M.view()));
    const Index m = M.view().rows;
    const Eigen::VectorXd b = Eigen::VectorXd::Random(m);
    Eigen::VectorXd x(m);
    chol.solve(b.data(), x.data());
    const Eigen::VectorXd expected = M.dense.llt().solve(b);
    // A well-conditioned (diagonally dominant) matrix of 126 unknowns: both solutions carry
    // rounding of a few ulps times the condition number (< 1e2 here).
    EXPECT_LT((x - expected).norm(), 1e-12 * expected.norm()) << seed;
    // A second factorisation of new values on the same pattern (the solver's use).
    BlockMatrix N = M;
    for (Scalar& v : N.values) v *= 2;
    ASSERT_TRUE(chol.factorize(N.view()));
    chol.solve(b.data(), x.data());
    EXPECT_LT((x - 0.5 * expected).norm(), 1e-12 * expected.norm()) << seed;
  }
}

TEST(BlockCholesky, BaselineAndAvx2VersionsGiveTheSameBits) {
  // The four-wide block updates run on SSE2 halves or AVX2 registers (no FMA): the same
  // operations in the same order, so the same bits.
  if (!cpu_has_avx2()) GTEST_SKIP() << "no AVX2 on this CPU";
  const BlockMatrix M = grid_matrix(9, 8, 0.0, 6);
  const Index m = M.view().rows;
  const Eigen::VectorXd b = Eigen::VectorXd::Random(m);
  auto solve = [&](bool baseline) {
    if (baseline)
      setenv("KINEMA_SIMD", "baseline", 1);
    else
      unsetenv("KINEMA_SIMD");
    BlockCholesky chol;
    chol.analyze(M.view());  // the instruction set is chosen here
    unsetenv("KINEMA_SIMD");
    EXPECT_TRUE(chol.factorize(M.view()));
    Eigen::VectorXd x(m);
    chol.solve(b.data(), x.data());
    return x;
  };
  const Eigen::VectorXd base = solve(true), wide = solve(false);
  EXPECT_EQ(std::memcmp(base.data(), wide.data(), sizeof(Scalar) * static_cast<size_t>(m)), 0);
  EXPECT_LT((base - M.dense.llt().solve(b)).norm(), 1e-12 * base.norm());
}

TEST(BlockCholesky, RefusesAnIndefiniteMatrix) {
  // Shifted far below zero on the diagonal: indefinite, so a pivot block fails.
  const BlockMatrix M = grid_matrix(5, 5, 0.0, 4);
  BlockMatrix N = M;
  const Index m = M.view().rows;
  for (Index r = 0; r < m; ++r)
    for (Index k = N.row_ptr[static_cast<size_t>(r)]; k < N.row_ptr[static_cast<size_t>(r) + 1]; ++k)
      if (N.col[static_cast<size_t>(k)] == r) N.values[static_cast<size_t>(k)] -= 1e3;
  BlockCholesky chol;
  chol.analyze(N.view());
  EXPECT_FALSE(chol.factorize(N.view()));
  ASSERT_TRUE(chol.factorize(M.view()));  // the same object recovers on a definite matrix
}

TEST(Bvh, TwoTreeDescentsFindEveryOverlappingPair) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<Scalar> u(0, 1);
  auto boxes = [&](int n, std::vector<Scalar>& lo, std::vector<Scalar>& hi) {
    lo.resize(3 * static_cast<size_t>(n));
    hi.resize(3 * static_cast<size_t>(n));
    for (size_t i = 0; i < lo.size(); ++i) {
      lo[i] = u(rng);
      hi[i] = lo[i] + 0.15 * u(rng);
    }
  };
  auto meet = [](const std::vector<Scalar>& lo, const std::vector<Scalar>& hi, size_t i, const std::vector<Scalar>& lo2,
                 const std::vector<Scalar>& hi2, size_t j) {
    for (int a = 0; a < 3; ++a)
      if (lo[3 * i + a] > hi2[3 * j + a] || lo2[3 * j + a] > hi[3 * i + a]) return false;
    return true;
  };
  std::vector<Scalar> alo, ahi, blo, bhi;
  boxes(300, alo, ahi);
  boxes(200, blo, bhi);
  const geometry::Bvh A(alo, ahi), B(blo, bhi);
  std::set<std::pair<Index, Index>> pairs, self;
  A.query_box_pairs(B, [&](Index i, Index j) { pairs.insert({i, j}); });
  size_t self_visits = 0;
  A.query_box_self([&](Index i, Index j) {
    ++self_visits;
    EXPECT_NE(i, j);
    self.insert({std::min(i, j), std::max(i, j)});
  });
  EXPECT_EQ(self_visits, self.size());  // every unordered pair at most once
  size_t expected_pairs = 0, expected_self = 0;
  for (size_t i = 0; i < 300; ++i) {
    for (size_t j = 0; j < 200; ++j)
      if (meet(alo, ahi, i, blo, bhi, j)) {
        ++expected_pairs;
        EXPECT_TRUE(pairs.count({static_cast<Index>(i), static_cast<Index>(j)})) << i << " " << j;
      }
    for (size_t j = i + 1; j < 300; ++j)
      if (meet(alo, ahi, i, alo, ahi, j)) {
        ++expected_self;
        EXPECT_TRUE(self.count({static_cast<Index>(i), static_cast<Index>(j)})) << i << " " << j;
      }
  }
  EXPECT_EQ(pairs.size(), expected_pairs);  // exact: no pair whose boxes do not overlap
  EXPECT_EQ(self.size(), expected_self);
  EXPECT_GT(expected_pairs, 50u);  // the boxes are dense enough for the test to mean something
  EXPECT_GT(expected_self, 50u);
}

}  // namespace kinema::contact
