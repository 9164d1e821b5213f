// The adjoint of the MAC-grid fluid step (grid/adjoint.h, Solver::step_adjoint) without Python:
// the projection's transpose passes the dot-product test <P a, b> = <a, P^T b> (2D and 3D, with
// obstacles and an open side), and the whole step's adjoint is deterministic (two calls give the
// same bits). Finite-difference checks of every scheme and input are in tests/test_diff_grid.py.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "core/errors.h"
#include "grid/solver.h"

namespace kinema::grid {
namespace {

Scalar dot(const std::array<std::vector<Scalar>, 3>& a, const std::array<std::vector<Scalar>, 3>& b) {
  Scalar s = 0;
  for (int c = 0; c < 3; ++c)
    for (size_t i = 0; i < a[c].size(); ++i) s += a[c][i] * b[c][i];
  return s;
}

TEST(GridAdjoint, ProjectionIsItsTranspose) {
  for (const auto& dims : {std::vector<Index>{16, 12}, std::vector<Index>{8, 6, 10}}) {
    const GridShape shape(dims);
    Model model = make_model(shape, 0.1);
    for (Index c = 0; c < shape.size(); c += 11) model.solid[c] = 1;
    Config config;
    config.tol = 1e-13;
    config.open[5] = true;  // the last axis's upper side
    Solver solver(model, config);
    Interrupt interrupt;
    State a = solver.make_state();
    solver.step(a, 1e-9, interrupt);  // builds the solid faces
    std::mt19937 rng(7);
    std::normal_distribution<Scalar> normal(0, 1);
    for (auto& u : a.velocity)
      for (Scalar& x : u) x = normal(rng);
    std::array<std::vector<Scalar>, 3> b;
    for (int c = 0; c < 3; ++c) {
      b[c].resize(a.velocity[c].size());
      for (Scalar& x : b[c]) x = normal(rng);
    }
    const std::array<std::vector<Scalar>, 3> a0 = a.velocity;
    std::fill(a.pressure.begin(), a.pressure.end(), 0);
    solver.apply_projection(a, 0.05, interrupt);
    std::array<std::vector<Scalar>, 3> pt_b = b;
    solver.projection_adjoint(pt_b, 0.05, interrupt);
    const Scalar lhs = dot(a.velocity, b), rhs = dot(a0, pt_b);
    // ~1e3 products of O(1) terms each side; the solves' error relative 1e3 tol (cond(A) < 1e3)
    const Scalar bound = 1e-9 * std::sqrt(dot(a0, a0) * dot(b, b));
    EXPECT_NEAR(lhs, rhs, bound) << shape.dim << "D";
    EXPECT_GT(std::fabs(lhs - dot(a0, b)), 1e3 * bound) << "P is not the identity";
  }
}

TEST(GridAdjoint, StepAdjointIsDeterministicAndChecksItsInput) {
  const GridShape shape(std::vector<Index>{12, 10});
  Config config;
  config.density = true;
  config.alpha = 0.3;
  config.viscosity = 1e-3;
  Solver solver(make_model(shape, 0.1), config);
  Interrupt interrupt;
  State before = solver.make_state();
  std::mt19937 rng(3);
  std::normal_distribution<Scalar> normal(0, 0.3);
  for (auto& u : before.velocity)
    for (Scalar& x : u) x = normal(rng);
  for (Scalar& x : before.density) x = std::fabs(normal(rng));
  State g1 = solver.make_state();
  for (auto& u : g1.velocity)
    for (Scalar& x : u) x = normal(rng);
  for (Scalar& x : g1.density) x = normal(rng);
  State g2 = g1, g3 = g1;
  Scalar nu1 = 0, nu2 = 0;
  solver.step_adjoint(before, 0.02, nullptr, g1, &nu1, nullptr, interrupt);
  solver.step_adjoint(before, 0.02, nullptr, g2, &nu2, nullptr, interrupt);
  EXPECT_EQ(nu1, nu2);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(g1.velocity[c], g2.velocity[c]);
  EXPECT_EQ(g1.density, g2.density);
  // without dL/dnu (only the advection's scratch recomputed) the other gradients are the same bits
  solver.step_adjoint(before, 0.02, nullptr, g3, nullptr, nullptr, interrupt);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(g1.velocity[c], g3.velocity[c]);
  EXPECT_EQ(g1.density, g3.density);
  EXPECT_THROW(solver.step_adjoint(before, 0, nullptr, g1, &nu1, nullptr, interrupt), InvalidArgument);
  Config confined = config;
  confined.vorticity_confinement = 0.1;
  Solver refused(make_model(shape, 0.1), confined);
  EXPECT_THROW(refused.check_differentiable(), InvalidArgument);
}

}  // namespace
}  // namespace kinema::grid
