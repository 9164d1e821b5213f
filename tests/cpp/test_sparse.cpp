// CHOLMOD wrapper, CSR spmv and Jacobi CG against dense Eigen references. Tolerances are
// kFwd * cond(A) * eps, the forward error of a backward-stable solve.
#include <gtest/gtest.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <utility>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "linalg/cg.h"
#include "linalg/cholmod_factor.h"
#include "linalg/csr.h"

namespace kinema {
namespace {

constexpr Scalar kEps = std::numeric_limits<Scalar>::epsilon();
constexpr Scalar kFwd = 20;

// Compressed storage that owns its arrays; symmetric, so CSR and CSC coincide.
struct Matrix {
  Index n = 0;
  std::vector<Index> ptr, idx;
  std::vector<Scalar> val;
  CscView csc() const { return {n, n, ptr.data(), idx.data(), val.data()}; }
  CsrView csr() const { return {n, n, ptr.data(), idx.data(), val.data()}; }
  MatrixX dense() const {
    MatrixX d = MatrixX::Zero(n, n);
    for (Index j = 0; j < n; ++j)
      for (Index p = ptr[j]; p < ptr[j + 1]; ++p) d(idx[p], j) += val[p];
    return d;
  }
};

Matrix from_dense(const MatrixX& d) {
  Matrix m;
  m.n = d.cols();
  m.ptr.push_back(0);
  for (Index j = 0; j < m.n; ++j) {
    for (Index i = 0; i < m.n; ++i)
      if (d(i, j) != 0) {
        m.idx.push_back(i);
        m.val.push_back(d(i, j));
      }
    m.ptr.push_back(static_cast<Index>(m.idx.size()));
  }
  return m;
}

// 5-point -lap on an m x m grid, Dirichlet, h = 1 (row i*m + j).
Matrix laplacian_2d(Index m) {
  Matrix a;
  a.n = m * m;
  a.ptr.push_back(0);
  for (Index i = 0; i < m; ++i)
    for (Index j = 0; j < m; ++j) {
      const Index r = i * m + j;
      auto add = [&](Index c, Scalar v) {
        a.idx.push_back(c);
        a.val.push_back(v);
      };
      if (i > 0) add(r - m, -1);
      if (j > 0) add(r - 1, -1);
      add(r, 4);
      if (j + 1 < m) add(r + 1, -1);
      if (i + 1 < m) add(r + m, -1);
      a.ptr.push_back(static_cast<Index>(a.idx.size()));
    }
  return a;
}

// B B^T + shift I with sparse random B (about 4 entries per column).
MatrixX random_spd(Index n, unsigned seed, Scalar shift = 0.01) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<Scalar> normal;
  std::uniform_int_distribution<Index> row(0, n - 1);
  MatrixX b = MatrixX::Zero(n, n);
  for (Index j = 0; j < n; ++j)
    for (int k = 0; k < 4; ++k) b(row(rng), j) = normal(rng);
  return b * b.transpose() + shift * MatrixX::Identity(n, n);
}

VectorX random_vector(Index n, unsigned seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<Scalar> normal;
  VectorX v(n);
  for (Index i = 0; i < n; ++i) v[i] = normal(rng);
  return v;
}

Scalar condition(const MatrixX& a) {
  const VectorX w = Eigen::SelfAdjointEigenSolver<MatrixX>(a, Eigen::EigenvaluesOnly).eigenvalues();
  return w[w.size() - 1] / w[0];
}

Scalar rel_err(const VectorX& x, const VectorX& ref) { return (x - ref).norm() / ref.norm(); }

TEST(CholmodFactor, MatchesDenseCholesky) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const MatrixX d = random_spd(200, seed);
    const Matrix a = from_dense(d);
    const VectorX b = random_vector(200, 10 + seed);
    CholmodFactor f(a.csc());
    VectorX x(200);
    f.solve(b.data(), x.data());
    const VectorX ref = d.llt().solve(b);
    const Scalar bound = kFwd * condition(d) * kEps;
    EXPECT_LE(rel_err(x, ref), bound) << "seed " << seed;
    EXPECT_TRUE(f.is_supernodal());
    EXPECT_EQ(f.size(), 200);
    const Scalar logdet = 2 * d.llt().matrixLLT().diagonal().array().log().sum();
    EXPECT_NEAR(f.log_determinant(), logdet, 1e-10 * std::abs(logdet));
  }
}

TEST(CholmodFactor, MultipleRightHandSidesColumnMajor) {
  const Matrix a = laplacian_2d(20);
  const MatrixX d = a.dense();
  MatrixX b(a.n, 5);
  for (int k = 0; k < 5; ++k) b.col(k) = random_vector(a.n, 20 + k);
  MatrixX x(a.n, 5);  // Eigen's default storage is column-major, as solve() expects
  CholmodFactor f(a.csc());
  f.solve(b.data(), x.data(), 5);
  const MatrixX ref = d.llt().solve(b);
  const Scalar bound = kFwd * condition(d) * kEps;
  for (int k = 0; k < 5; ++k)
    EXPECT_LE(rel_err(x.col(k), ref.col(k)), bound) << "column " << k;
}

TEST(CholmodFactor, RefactorUsesNewValues) {
  Matrix a = laplacian_2d(15);
  CholmodFactor f(a.csc());
  for (Index j = 0; j < a.n; ++j)
    for (Index p = a.ptr[j]; p < a.ptr[j + 1]; ++p)
      a.val[p] *= a.idx[p] == j ? 1.5 + 0.001 * j : 0.5;
  f.refactor(a.csc());
  const MatrixX d = a.dense();
  const VectorX b = random_vector(a.n, 30);
  VectorX x(a.n);
  f.solve(b.data(), x.data());
  EXPECT_LE(rel_err(x, d.llt().solve(b)), kFwd * condition(d) * kEps);
}

TEST(CholmodFactor, RefactorRejectsAnotherPattern) {
  const Matrix a = laplacian_2d(6);
  CholmodFactor f(a.csc());
  Matrix other = from_dense(a.dense() + 0.1 * MatrixX::Ones(a.n, a.n));
  EXPECT_THROW(f.refactor(other.csc()), InvalidArgument);
  const Matrix small = laplacian_2d(5);
  EXPECT_THROW(f.refactor(small.csc()), InvalidArgument);
}

// Tridiagonal -1, 2, -1 with pivot k forced to -1/2 (pivots d_j = (j+2)/(j+1)).
Matrix leading_minor_fails_at(Index k, Index n = 30) {
  MatrixX d = MatrixX::Zero(n, n);
  for (Index i = 0; i < n; ++i) {
    d(i, i) = 2;
    if (i + 1 < n) d(i, i + 1) = d(i + 1, i) = -1;
  }
  d(k, k) = static_cast<Scalar>(k) / (k + 1) - 0.5;
  return from_dense(d);
}

TEST(CholmodFactor, NotPositiveDefiniteReportsTheColumn) {
  for (Index k : {0, 1, 13, 29}) {
    const Matrix a = leading_minor_fails_at(k);
    try {
      CholmodFactor f(a.csc(), CholmodOrdering::Natural);
      ADD_FAILURE() << "no exception for k = " << k;
    } catch (const NotPositiveDefinite& e) {
      EXPECT_EQ(e.column, k);
    }
  }
  // Whatever the ordering, a hugely negative a_kk fails at column k.
  MatrixX d = random_spd(100, 7);
  d(42, 42) = -1e3 * (1 + d.cwiseAbs().maxCoeff());
  const Matrix a = from_dense(d);
  for (auto ordering : {CholmodOrdering::Default, CholmodOrdering::Amd}) {
    try {
      CholmodFactor f(a.csc(), ordering);
      ADD_FAILURE() << "no exception";
    } catch (const NotPositiveDefinite& e) {
      EXPECT_EQ(e.column, 42);
    }
  }
}

TEST(CholmodFactor, FailedRefactorThenRecovery) {
  const Matrix good = leading_minor_fails_at(0);  // same tridiagonal pattern
  Matrix spd = good;
  spd.val[0] = 2;
  CholmodFactor f(spd.csc(), CholmodOrdering::Natural);
  EXPECT_THROW(f.refactor(good.csc()), NotPositiveDefinite);
  VectorX b = VectorX::Ones(spd.n), x(spd.n);
  EXPECT_THROW(f.solve(b.data(), x.data()), KinemaError);
  f.refactor(spd.csc());
  f.solve(b.data(), x.data());
  EXPECT_LE((spd.dense() * x - b).norm(), 1e3 * kEps * b.norm());
}

TEST(CholmodFactor, RejectsMalformedInput) {
  const Matrix a = laplacian_2d(4);
  CscView v = a.csc();
  v.rows = 15;
  EXPECT_THROW(CholmodFactor{v}, InvalidArgument);  // not square
  Matrix bad = a;
  std::swap(bad.idx[0], bad.idx[1]);
  EXPECT_THROW(CholmodFactor{bad.csc()}, InvalidArgument);  // unsorted
  bad = a;
  bad.idx[1] = bad.idx[0];
  EXPECT_THROW(CholmodFactor{bad.csc()}, InvalidArgument);  // duplicate
  bad = a;
  bad.idx[3] = 16;
  EXPECT_THROW(CholmodFactor{bad.csc()}, InvalidArgument);  // out of range
  bad = a;
  std::swap(bad.ptr[2], bad.ptr[3]);
  EXPECT_THROW(CholmodFactor{bad.csc()}, InvalidArgument);  // col_ptr decreasing
  bad = a;
  bad.val[5] = std::numeric_limits<Scalar>::quiet_NaN();
  EXPECT_THROW(CholmodFactor{bad.csc()}, InvalidArgument);
  EXPECT_THROW(CholmodFactor{CscView{}}, InvalidArgument);  // empty
}

TEST(CholmodFactor, MovedFactorStillSolves) {
  const Matrix a = laplacian_2d(8);
  CholmodFactor f(a.csc());
  CholmodFactor g(std::move(f));
  VectorX b = VectorX::Ones(a.n), x(a.n);
  g.solve(b.data(), x.data());
  EXPECT_LE((a.dense() * x - b).norm(), 1e3 * kEps * b.norm());
}

// The int and long CHOLMOD interfaces run the same algorithm on the same ordering: the same
// permutation, the same failing column, and solutions equal to rounding.
TEST(CholmodFactor, IntAndLongInterfacesAgree) {
  const Matrix a = laplacian_2d(24);
  CholmodFactor auto_width(a.csc());
  CholmodFactor narrow(a.csc(), CholmodOrdering::Default, CholmodIndexWidth::Int);
  CholmodFactor wide(a.csc(), CholmodOrdering::Default, CholmodIndexWidth::Long);
  EXPECT_EQ(auto_width.index_bits(), 32);
  EXPECT_EQ(narrow.index_bits(), 32);
  EXPECT_EQ(wide.index_bits(), 64);
  EXPECT_EQ(narrow.factor_nonzeros(), wide.factor_nonzeros());
  EXPECT_TRUE(std::equal(narrow.permutation(), narrow.permutation() + a.n, wide.permutation()));
  const VectorX b = random_vector(a.n, 41);
  VectorX x32(a.n), x64(a.n);
  narrow.solve(b.data(), x32.data());
  wide.solve(b.data(), x64.data());
  const Scalar bound = kFwd * condition(a.dense()) * kEps;
  EXPECT_LE(rel_err(x32, x64), bound);
  EXPECT_NEAR(narrow.log_determinant(), wide.log_determinant(),
              1e-12 * std::abs(wide.log_determinant()));
  for (auto width : {CholmodIndexWidth::Int, CholmodIndexWidth::Long}) {
    try {
      CholmodFactor f(leading_minor_fails_at(13).csc(), CholmodOrdering::Natural, width);
      ADD_FAILURE() << "no exception";
    } catch (const NotPositiveDefinite& e) {
      EXPECT_EQ(e.column, 13);
    }
  }
}

TEST(CholmodFactor, SupernodalOnLargeLaplacian) {
  const Matrix a = laplacian_2d(256);
  CholmodFactor f(a.csc());
  EXPECT_TRUE(f.is_supernodal());
  const VectorX b = random_vector(a.n, 40);
  VectorX x(a.n), ax(a.n);
  f.solve(b.data(), x.data());
  spmv(a.csr(), x.data(), ax.data());
  EXPECT_LE((ax - b).norm() / b.norm(), 1e3 * kEps);
}

TEST(Spmv, MatchesEigenAndIsThreadIndependent) {
  const Matrix a = laplacian_2d(100);  // 10^4 rows: parallel
  const VectorX x = random_vector(a.n, 50);
  const Eigen::Map<const SparseMatrix> s(a.n, a.n, a.ptr.back(), a.ptr.data(), a.idx.data(),
                                         a.val.data());
  const VectorX ref = s * x;
  const int saved = num_threads();
  std::vector<VectorX> ys;
  for (int t : {1, 2}) {
    set_num_threads(t);
    VectorX y(a.n);
    spmv(a.csr(), x.data(), y.data());
    ys.push_back(y);
  }
  set_num_threads(saved);
  EXPECT_LE((ys[0] - ref).norm(), 8 * kEps * ref.norm());
  EXPECT_TRUE((ys[0].array() == ys[1].array()).all());
}

TEST(CgCsr, ConvergesWithTrueResidual) {
  const Matrix a = laplacian_2d(40);
  const VectorX b = random_vector(a.n, 60);
  for (bool jacobi : {false, true}) {
    VectorX x = VectorX::Zero(a.n), ax(a.n);
    Interrupt none;
    const SolveInfo info = cg_csr(a.csr(), b.data(), x.data(), jacobi, {1e-10, 0}, none);
    spmv(a.csr(), x.data(), ax.data());
    const Scalar residual = (b - ax).norm() / b.norm();
    EXPECT_TRUE(info.converged);
    EXPECT_LE(residual, 1.01e-10);
    EXPECT_NEAR(info.residual, residual, 1e-3 * residual);
  }
}

TEST(CgCsr, JacobiNeedsPositiveDiagonalAndInterruptStops) {
  Matrix a = laplacian_2d(5);
  VectorX b = VectorX::Ones(a.n), x = VectorX::Zero(a.n);
  Interrupt none;
  a.val[a.ptr[3] + 1] = 0;  // row 3: entries (3-1), (3,3), ...: the diagonal is second
  ASSERT_EQ(a.idx[a.ptr[3] + 1], 3);
  EXPECT_THROW(cg_csr(a.csr(), b.data(), x.data(), true, {}, none), InvalidArgument);

  const Matrix big = laplacian_2d(64);
  VectorX bb = VectorX::Ones(big.n), xx = VectorX::Zero(big.n);
  int polls = 0;
  Interrupt stop([&polls] { return ++polls >= 3; }, 0.0);
  EXPECT_THROW(cg_csr(big.csr(), bb.data(), xx.data(), false, {1e-14, 0}, stop), Interrupted);
  EXPECT_EQ(polls, 3);
}

}  // namespace
}  // namespace kinema
