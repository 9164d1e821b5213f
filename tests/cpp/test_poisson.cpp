// The grid Poisson core, tested without Python: matrix-free product equals the assembled one,
// restriction is the scaled transpose of prolongation, the V-cycle is symmetric, and MGPCG
// reaches the manufactured solution with second-order accuracy.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <random>
#include <vector>

#include "core/simd.h"
#include "poisson/poisson_solver.h"

namespace kinema {
namespace {

std::vector<std::uint8_t> random_solid(Index n, double fraction, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<std::uint8_t> solid(n);
  for (auto& s : solid) s = u(rng) < fraction;
  return solid;
}

std::vector<Scalar> random_vector(Index n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g;
  std::vector<Scalar> v(n);
  for (auto& x : v) x = g(rng);
  return v;
}

Scalar dot(const std::vector<Scalar>& a, const std::vector<Scalar>& b) {
  Scalar s = 0;
  for (size_t i = 0; i < a.size(); ++i) s += a[i] * b[i];
  return s;
}

// 2^d <R f, c> = <f, P c> on the first two levels of op's hierarchy (fluid entries of f only).
void expect_restriction_is_scaled_transpose(const PoissonOperator& op, unsigned seed) {
  Multigrid mg(op, MultigridOptions{2, 2, 64});
  ASSERT_GE(mg.levels(), 2);
  auto fine = random_vector(op.size(), seed);
  for (Index c = 0; c < op.size(); ++c)
    if (!op.fluid(c)) fine[c] = 0;
  const Index nc = mg.level(1).size();
  const auto coarse = random_vector(nc, seed + 1);
  std::vector<Scalar> Rf(nc), Pc(op.size(), 0);
  mg.restrict_residual(0, fine.data(), Rf.data());
  mg.prolong_add(0, coarse.data(), Pc.data());
  const Scalar scale = op.shape().dim == 3 ? 8 : 4;
  const Scalar lhs = scale * dot(Rf, coarse), rhs = dot(fine, Pc);
  EXPECT_NEAR(lhs, rhs, 1e-12 * std::abs(rhs));
}

// <V a, b> = <a, V b> and <V a, a> > 0 for the V-cycle V of op (on the range of A).
void expect_vcycle_symmetric(const PoissonOperator& op, unsigned seed) {
  Multigrid mg(op, MultigridOptions{2, 2, 64});
  auto a = random_vector(op.size(), seed), b = random_vector(op.size(), seed + 1);
  op.project(a.data());
  op.project(b.data());
  std::vector<Scalar> Va(op.size()), Vb(op.size());
  mg.vcycle(a.data(), Va.data());
  mg.vcycle(b.data(), Vb.data());
  EXPECT_NEAR(dot(Va, b), dot(a, Vb), 1e-12 * std::abs(dot(Va, b)));
  EXPECT_GT(dot(Va, a), 0);
}

class PoissonShapes : public ::testing::TestWithParam<std::tuple<std::vector<Index>, Boundary>> {};

TEST_P(PoissonShapes, MatrixFreeEqualsAssembled) {
  const auto& [dims, bc] = GetParam();
  const GridShape shape(dims);
  const auto solid = random_solid(shape.size(), 0.15, 1);
  const PoissonOperator op(shape, 0.3, bc, solid.data());
  const auto x = random_vector(shape.size(), 2);
  std::vector<Scalar> y(shape.size());
  op.apply(x.data(), y.data());
  const CsrArrays A = op.assemble();
  for (Index r = 0; r < A.rows; ++r) {
    Scalar s = 0;
    for (Index p = A.row_ptr[r]; p < A.row_ptr[r + 1]; ++p) s += A.values[p] * x[A.col_index[p]];
    ASSERT_NEAR(s, y[r], 1e-12 * (1 + std::abs(y[r]))) << "row " << r;
  }
}

TEST_P(PoissonShapes, RestrictionIsScaledTransposeOfProlongation) {
  const auto& [dims, bc] = GetParam();
  const GridShape shape(dims);
  const auto solid = random_solid(shape.size(), 0.1, 3);
  expect_restriction_is_scaled_transpose(PoissonOperator(shape, 0.3, bc, solid.data()), 4);
}

TEST_P(PoissonShapes, VCycleIsSymmetric) {
  const auto& [dims, bc] = GetParam();
  const GridShape shape(dims);
  const auto solid = random_solid(shape.size(), 0.1, 6);
  expect_vcycle_symmetric(PoissonOperator(shape, 0.3, bc, solid.data()), 7);
}

INSTANTIATE_TEST_SUITE_P(
    Grids, PoissonShapes,
    ::testing::Combine(::testing::Values(std::vector<Index>{29, 24}, std::vector<Index>{32, 32},
                                         std::vector<Index>{11, 9, 12}, std::vector<Index>{16, 16, 16}),
                       ::testing::Values(Boundary::Dirichlet, Boundary::Neumann)));

// Mixed walls (Dirichlet on some sides, Neumann on the others: km.grid's open sides), with and
// without solids (without them the separable fast transfers run, which take the per-wall
// ghost signs): the same structural properties, and the assembled matrix symmetric.
class MixedWalls : public ::testing::TestWithParam<std::tuple<std::vector<Index>, int, bool>> {};

TEST_P(MixedWalls, OperatorAndTransfersStayConsistent) {
  const auto& [dims, walls, with_solid] = GetParam();
  const GridShape shape(dims);
  const auto solid = random_solid(shape.size(), 0.1, 11);
  const PoissonOperator op(shape, 0.3, Boundary::Neumann, with_solid ? solid.data() : nullptr, 0, walls);
  // one Dirichlet side makes a solid-free grid nonsingular (pockets enclosed by solids stay so)
  if (!with_solid) ASSERT_FALSE(op.singular());
  const auto x = random_vector(shape.size(), 12);
  std::vector<Scalar> y(shape.size());
  op.apply(x.data(), y.data());
  const CsrArrays A = op.assemble();
  std::vector<std::vector<std::pair<Index, Scalar>>> rows(A.rows);
  for (Index r = 0; r < A.rows; ++r) {
    Scalar s = 0;
    for (Index p = A.row_ptr[r]; p < A.row_ptr[r + 1]; ++p) {
      s += A.values[p] * x[A.col_index[p]];
      rows[r].emplace_back(A.col_index[p], A.values[p]);
    }
    ASSERT_NEAR(s, y[r], 1e-12 * (1 + std::abs(y[r]))) << "row " << r;
  }
  for (Index r = 0; r < A.rows; ++r)
    for (const auto& [c, v] : rows[r]) {
      const auto it = std::find_if(rows[c].begin(), rows[c].end(), [&](const auto& e) { return e.first == r; });
      ASSERT_TRUE(it != rows[c].end() && it->second == v) << "A(" << r << ", " << c << ") not symmetric";
    }
  EXPECT_EQ(op.coarsened().dirichlet_walls(), op.dirichlet_walls());
  expect_restriction_is_scaled_transpose(op, 13);
  expect_vcycle_symmetric(op, 15);
}

// Walls are bits 2*axis + side of the internal axes (a 2D grid's axes are 1 and 2): the upper
// wall of the second axis alone (an open top), both ends of the row axis, and three sides.
INSTANTIATE_TEST_SUITE_P(
    Grids, MixedWalls,
    ::testing::Combine(::testing::Values(std::vector<Index>{29, 24}, std::vector<Index>{32, 32},
                                         std::vector<Index>{11, 9, 12}, std::vector<Index>{16, 16, 16}),
                       ::testing::Values(1 << 5, (1 << 4) | (1 << 5), (1 << 3) | (1 << 4) | (1 << 2)),
                       ::testing::Bool()));

// -lap u = 3 pi^2 u for u = sin(pi x) sin(pi y) sin(pi z); the error falls by ~4 per halving of h.
TEST(Mgpcg, ManufacturedSolutionSecondOrder) {
  std::vector<Scalar> errors;
  for (Index n : {8, 16, 32}) {
    const GridShape shape({n, n, n});
    const Scalar h = 1.0 / n;
    std::vector<Scalar> f(shape.size()), exact(shape.size()), u(shape.size(), 0);
    for (Index i = 0; i < n; ++i)
      for (Index j = 0; j < n; ++j)
        for (Index k = 0; k < n; ++k) {
          const Scalar e = std::sin(M_PI * (i + 0.5) * h) * std::sin(M_PI * (j + 0.5) * h) *
                           std::sin(M_PI * (k + 0.5) * h);
          exact[shape.index(i, j, k)] = e;
          f[shape.index(i, j, k)] = 3 * M_PI * M_PI * e;
        }
    PoissonSolver solver(shape, h, Boundary::Dirichlet, nullptr, 0, PoissonConfig{});
    Interrupt none;
    const SolveInfo info = solver.solve(f.data(), u.data(), IterativeOptions{1e-12, 0}, none);
    ASSERT_TRUE(info.converged);
    EXPECT_LE(info.iterations, 12);
    Scalar err = 0;
    for (Index c = 0; c < shape.size(); ++c) err = std::max(err, std::abs(u[c] - exact[c]));
    errors.push_back(err);
  }
  for (size_t l = 1; l < errors.size(); ++l) {
    const Scalar order = std::log2(errors[l - 1] / errors[l]);
    EXPECT_NEAR(order, 2.0, 0.2) << "between levels " << l - 1 << " and " << l;
  }
}

// A few scattered solid cells, which leave most rows plain, and one whole solid row (j = 2 of
// the middle plane), which gives the rows beside it one stencil with a coupling missing (the
// rows along the domain's faces have one too): the three kinds of row the passes tell apart.
std::vector<std::uint8_t> scattered_solids_and_a_solid_row(const GridShape& shape) {
  std::vector<std::uint8_t> solid(shape.size(), 0);
  for (Index c = 0; c < shape.size(); c += 1999) solid[c] = 1;
  const Index row = (shape.n[0] / 2) * shape.n[1] + 2;
  for (Index k = 0; k < shape.n[2]; ++k) solid[row * shape.n[2] + k] = 1;
  return solid;
}

// The AVX2 and baseline versions of the plain-stencil rows do the same operations in the same
// order (no FMA), so apply and residual must agree bit for bit, on fast rows and masked ones.
TEST(PoissonOperator, Avx2RowsEqualBaselineBitwise) {
  if (!cpu_has_avx2()) GTEST_SKIP() << "this CPU has no AVX2";
  // Rows of 37 cells take the vector loop with scalar ends, rows of 36 whole vectors only, rows
  // of 4 a single vector.
  for (const auto& dims : {std::vector<Index>{67, 45}, std::vector<Index>{19, 23, 37}, std::vector<Index>{19, 23, 36},
                           std::vector<Index>{9, 8, 4}}) {
    for (Boundary bc : {Boundary::Dirichlet, Boundary::Neumann, Boundary::Periodic}) {
      const GridShape shape(dims);
      const auto solid = scattered_solids_and_a_solid_row(shape);
      setenv("KINEMA_SIMD", "baseline", 1);
      const PoissonOperator baseline(shape, 0.3, bc, solid.data(), 0.5);
      unsetenv("KINEMA_SIMD");
      const PoissonOperator wide(shape, 0.3, bc, solid.data(), 0.5);
      ASSERT_FALSE(baseline.avx2());
      ASSERT_TRUE(wide.avx2());
      const auto x = random_vector(shape.size(), 3), b = random_vector(shape.size(), 4);
      std::vector<Scalar> y0(shape.size()), y1(shape.size()), r0(shape.size()), r1(shape.size());
      baseline.apply(x.data(), y0.data());
      wide.apply(x.data(), y1.data());
      baseline.residual(b.data(), x.data(), r0.data());
      wide.residual(b.data(), x.data(), r1.data());
      // Both against the assembled matrix, to rounding: a mistake shared by the two row
      // versions (the end cells, the row kinds) shows here.
      const CsrArrays A = wide.assemble();
      for (Index c = 0; c < shape.size(); ++c) {
        ASSERT_EQ(y0[c], y1[c]) << "apply, cell " << c;
        ASSERT_EQ(r0[c], r1[c]) << "residual, cell " << c;
        Scalar ax = 0, scale = 0;
        for (Index p = A.row_ptr[c]; p < A.row_ptr[c + 1]; ++p) {
          ax += A.values[p] * x[A.col_index[p]];
          scale += std::abs(A.values[p] * x[A.col_index[p]]);
        }
        ASSERT_NEAR(y1[c], ax, 1e-14 * scale) << "apply against the matrix, cell " << c;
        ASSERT_NEAR(r1[c], wide.fluid(c) ? b[c] - ax : 0, 1e-14 * (scale + std::abs(b[c])))
            << "residual against the matrix, cell " << c;
      }
    }
  }
}

// One red-black sweep, written plainly from the assembled matrix: every cell of the first
// colour in index order, then every cell of the second.
std::vector<Scalar> reference_sweep(const PoissonOperator& op, const std::vector<Scalar>& b,
                                    std::vector<Scalar> x, int first_color) {
  const CsrArrays A = op.assemble();
  const GridShape& s = op.shape();
  for (int color : {first_color, 1 - first_color}) {
    for (Index i = 0; i < s.n[0]; ++i)
      for (Index j = 0; j < s.n[1]; ++j)
        for (Index k = 0; k < s.n[2]; ++k) {
          const Index c = s.index(i, j, k);
          if (((i + j + k) & 1) != color || !op.fluid(c)) continue;
          Scalar off = 0, diag = 0;
          for (Index p = A.row_ptr[c]; p < A.row_ptr[c + 1]; ++p) {
            if (A.col_index[p] == c) diag = A.values[p];
            else off += A.values[p] * x[A.col_index[p]];
          }
          x[c] = diag > 0 ? (b[c] - off) / diag : 0;
        }
  }
  return x;
}

// The fused, threaded sweep must be the plain two-pass red-black sweep: against the reference
// to rounding (its sums run in another order), and bitwise the same whatever the thread count
// and the instruction set (AVX2 blended rows or the scalar loop), since each cell's update reads
// the same values in every schedule.
TEST(PoissonOperator, FusedSweepIsTheRedBlackSweep) {
  const int saved_threads = num_threads();
  // Grids above PoissonOperator::parallel()'s threshold, to run threaded, and small odd ones.
  // Rows of 32, 8 and 44 cells take the whole-vector rows, the others the odd-start ones (rows
  // of 4 and 3 cells: no vector at all).
  // Red-black needs an even number of cells on every periodic axis: those grids also run periodic.
  for (const auto& dims : {std::vector<Index>{35, 30, 34}, std::vector<Index>{41, 36, 27},
                           std::vector<Index>{5, 9, 11}, std::vector<Index>{200, 190},
                           std::vector<Index>{45, 38}, std::vector<Index>{36, 30, 34},
                           std::vector<Index>{36, 31, 32}, std::vector<Index>{20, 18, 8}, std::vector<Index>{190, 44},
                           std::vector<Index>{12, 10, 4}, std::vector<Index>{6, 5, 3}}) {
    const GridShape shape(dims);
    const auto solid = scattered_solids_and_a_solid_row(shape);
    const auto b = random_vector(shape.size(), 11), x0 = random_vector(shape.size(), 12);
    for (auto [first, bc] : {std::pair{0, Boundary::Dirichlet}, std::pair{1, Boundary::Dirichlet},
                             std::pair{0, Boundary::Neumann}, std::pair{1, Boundary::Periodic}}) {
      if (bc == Boundary::Periodic && std::any_of(dims.begin(), dims.end(), [](Index n) { return n % 2; })) continue;
      const PoissonOperator plain(shape, 0.3, bc, solid.data(), 0.25);
      const auto expected = reference_sweep(plain, b, x0, first);
      std::vector<Scalar> first_result;
      for (bool baseline : {false, true}) {
        if (baseline) setenv("KINEMA_SIMD", "baseline", 1);
        const PoissonOperator op(shape, 0.3, bc, solid.data(), 0.25);
        unsetenv("KINEMA_SIMD");
        ASSERT_EQ(op.avx2(), !baseline && cpu_has_avx2());
        for (int threads : {1, 2, 3}) {
          set_num_threads(threads);
          auto x = x0;
          op.sweep(b.data(), x.data(), first);
          for (Index c = 0; c < shape.size(); ++c)
            ASSERT_NEAR(x[c], expected[c], 1e-12 * (1 + std::abs(expected[c])))
                << "cell " << c << ", threads " << threads << ", baseline " << baseline;
          if (first_result.empty()) first_result = x;
          for (Index c = 0; c < shape.size(); ++c)
            ASSERT_EQ(x[c], first_result[c]) << "cell " << c << ", threads " << threads << ", baseline "
                                             << baseline;
        }
      }
    }
  }
  set_num_threads(saved_threads);
}

// The 3D apply and residual with non-temporal stores (switched on here for a small grid) give
// the products of the cached stores and of the baseline bit for bit, at any thread count.
TEST(PoissonOperator, StreamingStoresChangeNoBit) {
  if (!cpu_has_avx2()) GTEST_SKIP() << "this CPU has no AVX2";
  const int saved_threads = num_threads();
  // Above PoissonOperator::parallel()'s threshold; rows of whole vectors (32 cells, written
  // by streaming stores) and not (31 cells, written through the cache).
  for (const auto& dims : {std::vector<Index>{40, 30, 32}, std::vector<Index>{40, 30, 31}}) {
    const GridShape shape(dims);
    const auto solid = scattered_solids_and_a_solid_row(shape);
    setenv("KINEMA_SIMD", "baseline", 1);
    const PoissonOperator baseline(shape, 0.3, Boundary::Neumann, solid.data());
    unsetenv("KINEMA_SIMD");
    PoissonOperator op(shape, 0.3, Boundary::Neumann, solid.data());
    ASSERT_FALSE(op.stream_stores());  // 1 MB per array: far below kStreamBytes
    const auto x = random_vector(shape.size(), 13), b = random_vector(shape.size(), 14);
    std::vector<Scalar> y0(shape.size()), r0(shape.size());
    baseline.apply(x.data(), y0.data());
    baseline.residual(b.data(), x.data(), r0.data());
    for (bool stream : {false, true}) {
      op.set_stream_stores(stream);
      ASSERT_EQ(op.stream_stores(), stream);
      for (int threads : {1, 2, 3}) {
        set_num_threads(threads);
        std::vector<Scalar> y(shape.size()), r(shape.size());
        op.apply(x.data(), y.data());
        op.residual(b.data(), x.data(), r.data());
        for (Index c = 0; c < shape.size(); ++c) {
          ASSERT_EQ(y[c], y0[c]) << "apply, cell " << c << ", stream " << stream;
          ASSERT_EQ(r[c], r0[c]) << "residual, cell " << c << ", stream " << stream;
        }
      }
    }
  }
  set_num_threads(saved_threads);
}

TEST(PoissonOperator, RejectsBadSpacing) {
  const GridShape shape({4, 4});
  EXPECT_THROW(PoissonOperator(shape, 0.0, Boundary::Dirichlet, nullptr), InvalidArgument);
  EXPECT_THROW(PoissonOperator(shape, -1.0, Boundary::Dirichlet, nullptr), InvalidArgument);
  EXPECT_THROW(GridShape(std::vector<Index>{4}), InvalidArgument);
}

}  // namespace
}  // namespace kinema
