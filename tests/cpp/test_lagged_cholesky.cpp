// LaggedCholesky: when it factorises and when it reuses a factor, and that every answer meets
// the requested tolerance, on a 1D Laplacian-plus-mass family A(s) = M + s L whose values
// drift with s like a Newton matrix across iterations.
#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "linalg/lagged_cholesky.h"

namespace kinema {
namespace {

// Tridiagonal A = I + s L (L the 1D Dirichlet Laplacian), full symmetric CSR.
struct Tridiagonal {
  Index n;
  std::vector<Index> ptr, idx;
  std::vector<Scalar> val;
  Tridiagonal(Index size, Scalar s, Scalar shift = 1) : n(size) {
    ptr.push_back(0);
    for (Index i = 0; i < n; ++i) {
      if (i > 0) idx.push_back(i - 1), val.push_back(-s);
      idx.push_back(i), val.push_back(shift + 2 * s);
      if (i + 1 < n) idx.push_back(i + 1), val.push_back(-s);
      ptr.push_back(static_cast<Index>(idx.size()));
    }
  }
  CsrView view() const { return {n, n, ptr.data(), idx.data(), val.data()}; }
  // ||b - A x|| / ||b||
  Scalar residual(const std::vector<Scalar>& b, const std::vector<Scalar>& x) const {
    Scalar r2 = 0, b2 = 0;
    for (Index i = 0; i < n; ++i) {
      Scalar ax = 0;
      for (Index p = ptr[i]; p < ptr[i + 1]; ++p) ax += val[p] * x[idx[p]];
      r2 += (b[i] - ax) * (b[i] - ax);
      b2 += b[i] * b[i];
    }
    return std::sqrt(r2 / b2);
  }
};

TEST(LaggedCholesky, ReusesTheFactorWhileItPreconditionsWell) {
  const Index n = 200;
  std::vector<Scalar> b(n), x(n, 0);
  for (Index i = 0; i < n; ++i) b[i] = std::sin(0.1 * i) + 1;
  LaggedCholesky solver;
  // One solve from x = 0; the answer must meet the tolerance whichever way it was found.
  auto solve = [&](const Tridiagonal& A, bool reuse, Index cap) {
    LaggedSolveStats s;
    std::fill(x.begin(), x.end(), 0);
    EXPECT_TRUE(solver.solve(A.view(), b.data(), x.data(), reuse, 1e-10, cap, s));
    EXPECT_LT(A.residual(b, x), 1e-10);
    return s;
  };

  const Tridiagonal A0(n, 100.0);
  EXPECT_EQ(solve(A0, true, 25).factorizations, 1);  // nothing to reuse yet

  // 1% drift: the old factor preconditions A1 to a few PCG iterations, no factorisation.
  const Tridiagonal A1(n, 101.0);
  const LaggedSolveStats s1 = solve(A1, true, 25);
  EXPECT_EQ(s1.factorizations, 0);
  EXPECT_GT(s1.pcg_iterations, 0);
  EXPECT_LE(s1.pcg_iterations, 8);

  // reuse = false always factorises.
  const LaggedSolveStats s2 = solve(A1, false, 25);
  EXPECT_EQ(s2.factorizations, 1);
  EXPECT_EQ(s2.pcg_iterations, 0);

  // A 100x change: PCG with the stale factor cannot reach 1e-10 in 3 iterations, so the
  // solver refactorises and still answers to the tolerance.
  const LaggedSolveStats s3 = solve(Tridiagonal(n, 1e4), true, 3);
  EXPECT_EQ(s3.factorizations, 1);
  EXPECT_EQ(s3.pcg_iterations, 3);
}

TEST(LaggedCholesky, RefactorisesAfterASlowSolve) {
  const Index n = 200;
  std::vector<Scalar> b(n, 1.0), x(n, 0);
  LaggedCholesky solver;
  LaggedSolveStats s;
  ASSERT_TRUE(solver.solve(Tridiagonal(n, 100.0).view(), b.data(), x.data(), true, 1e-10, 40, s));
  // 2x drift: PCG converges, but needs more than half the cap: the next call refactorises
  // without trying PCG first.
  const Tridiagonal A1(n, 200.0, 0.5);
  LaggedSolveStats s1, s2;
  std::fill(x.begin(), x.end(), 0);
  ASSERT_TRUE(solver.solve(A1.view(), b.data(), x.data(), true, 1e-10, 12, s1));
  ASSERT_EQ(s1.factorizations, 0) << "PCG iterations " << s1.pcg_iterations;
  ASSERT_GT(s1.pcg_iterations, 6);
  ASSERT_TRUE(solver.solve(A1.view(), b.data(), x.data(), true, 1e-10, 12, s2));
  EXPECT_EQ(s2.factorizations, 1);
  EXPECT_EQ(s2.pcg_iterations, 0);
}

TEST(LaggedCholesky, IndefiniteMatrixIsReported) {
  const Index n = 50;
  std::vector<Scalar> b(n, 1.0), x(n, 0);
  LaggedCholesky solver;
  LaggedSolveStats s;
  ASSERT_TRUE(solver.solve(Tridiagonal(n, 1.0).view(), b.data(), x.data(), true, 1e-10, 25, s));
  // shift -3: A = -3 I + L has eigenvalues in (-3, 1). PCG meets negative curvature (proof
  // enough) and keeps the lagged factor; a forced factorisation finds a bad pivot and drops it.
  const Tridiagonal bad(n, 1.0, -3.0);
  LaggedSolveStats s1, s2;
  EXPECT_FALSE(solver.solve(bad.view(), b.data(), x.data(), true, 1e-10, 25, s1));
  EXPECT_EQ(s1.factorizations, 0);
  EXPECT_TRUE(solver.has_factor());
  EXPECT_FALSE(solver.solve(bad.view(), b.data(), x.data(), false, 1e-10, 25, s2));
  EXPECT_EQ(s2.factorizations, 1);
  EXPECT_FALSE(solver.has_factor());
  const Tridiagonal good(n, 2.0);
  LaggedSolveStats s3;
  ASSERT_TRUE(solver.solve(good.view(), b.data(), x.data(), true, 1e-10, 25, s3));
  EXPECT_EQ(s3.factorizations, 1);  // no valid factor to reuse
  EXPECT_LT(good.residual(b, x), 1e-13);
}

}  // namespace
}  // namespace kinema
