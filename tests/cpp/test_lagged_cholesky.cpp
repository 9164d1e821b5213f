// LaggedCholesky: when it factorises and when it reuses a factor, and that every answer meets
// the requested tolerance, on a 1D Laplacian-plus-mass family A(s) = shift I + s L whose values
// drift with s like a Newton matrix across iterations.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "linalg/lagged_cholesky.h"

namespace kinema {
namespace {

// Tridiagonal A = shift I + s L (L the 1D Dirichlet Laplacian), full symmetric CSR.
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

// One solver and a right-hand side; run() solves from x = 0 to 1e-10 and checks the answer
// whenever the matrix was found positive definite.
struct Sequence {
  std::vector<Scalar> b, x;
  LaggedCholesky solver;
  bool definite = false;
  explicit Sequence(Index n) : b(n), x(n) {
    for (Index i = 0; i < n; ++i) b[i] = std::sin(0.1 * i) + 1;
  }
  LaggedSolveStats run(const Tridiagonal& A, bool reuse, Index cap) {
    LaggedSolveStats s;
    std::fill(x.begin(), x.end(), 0);
    definite = solver.solve(A.view(), b.data(), x.data(), reuse, 1e-10, cap, s);
    if (definite) EXPECT_LT(A.residual(b, x), 1e-10);
    return s;
  }
};

void expect_counts(const LaggedSolveStats& s, Index factorizations, Index pcg_iterations) {
  EXPECT_EQ(s.factorizations, factorizations);
  EXPECT_EQ(s.pcg_iterations, pcg_iterations);
}

TEST(LaggedCholesky, ReusesTheFactorWhileItPreconditionsWell) {
  const Index n = 200;
  Sequence seq(n);
  EXPECT_EQ(seq.run(Tridiagonal(n, 100.0), true, 25).factorizations, 1);  // nothing to reuse yet

  // 1% drift: the old factor preconditions A1 to a few PCG iterations, no factorisation.
  const Tridiagonal A1(n, 101.0);
  const LaggedSolveStats s1 = seq.run(A1, true, 25);
  EXPECT_EQ(s1.factorizations, 0);
  EXPECT_GT(s1.pcg_iterations, 0);
  EXPECT_LE(s1.pcg_iterations, 8);

  // reuse = false always factorises.
  expect_counts(seq.run(A1, false, 25), 1, 0);

  // A 100x change: PCG with the stale factor cannot reach 1e-10 in 3 iterations, so the
  // solver refactorises and still answers to the tolerance.
  expect_counts(seq.run(Tridiagonal(n, 1e4), true, 3), 1, 3);
  EXPECT_TRUE(seq.definite);
}

TEST(LaggedCholesky, RefactorisesAfterASlowSolve) {
  const Index n = 200;
  Sequence seq(n);
  seq.run(Tridiagonal(n, 100.0), true, 40);
  // 2x drift: PCG converges, but needs more than half the cap: the next call refactorises
  // without trying PCG first.
  const Tridiagonal A1(n, 200.0, 0.5);
  const LaggedSolveStats s1 = seq.run(A1, true, 24);
  ASSERT_EQ(s1.factorizations, 0) << "PCG iterations " << s1.pcg_iterations;
  ASSERT_GT(s1.pcg_iterations, 24 / 2);
  expect_counts(seq.run(A1, true, 24), 1, 0);
}

TEST(LaggedCholesky, IndefiniteMatrixIsReported) {
  const Index n = 50;
  Sequence seq(n);
  seq.run(Tridiagonal(n, 1.0), true, 25);
  EXPECT_TRUE(seq.definite && seq.solver.has_factor());
  // shift -3: A = -3 I + L has eigenvalues in (-3, 1). PCG meets negative curvature (proof
  // enough) and keeps the lagged factor; a forced factorisation finds a bad pivot and drops it.
  const Tridiagonal bad(n, 1.0, -3.0);
  EXPECT_EQ(seq.run(bad, true, 25).factorizations, 0);
  EXPECT_FALSE(seq.definite);
  EXPECT_TRUE(seq.solver.has_factor());
  EXPECT_EQ(seq.run(bad, false, 25).factorizations, 1);
  EXPECT_FALSE(seq.definite);
  EXPECT_FALSE(seq.solver.has_factor());
  EXPECT_EQ(seq.run(Tridiagonal(n, 2.0), true, 25).factorizations, 1);  // nothing valid to reuse
  EXPECT_TRUE(seq.definite);
}

}  // namespace
}  // namespace kinema
