// The MAC-grid fluid solver (grid/solver.h) in its four roles, without Python: a copy of the
// State resumes bit for bit on a second Solver built from the same Model and Config (the State
// holds all a step reads from the past), a failed step leaves the State as it was, values are
// checked where they enter (dt, the State's sizes, the Config), and stable_dt is the CFL rule
// dt = cfl h / (max|u| + sqrt(5 h |g|)) of Bridson (2015), Sec. 3.2.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "core/errors.h"
#include "grid/solver.h"

namespace kinema::grid {
namespace {

// Every evolving field in use; gravity along the last user axis (internal axis 2).
Config smoke_config() {
  Config c;
  c.density = c.temperature = true;
  c.alpha = 0.1;
  c.beta = 1.0;
  c.gravity[2] = -9.8;
  c.viscosity = 1e-3;
  c.vorticity_confinement = 0.2;
  return c;
}

Model box_with_obstacle(const GridShape& shape) {
  Model m = make_model(shape, 1.0 / static_cast<Scalar>(shape.n[2]));
  for (Index c = 0; c < shape.size(); c += 7) m.solid[c] = (c / 7) % 3 == 0;
  return m;
}

void stir(State& s, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<Scalar> normal(0, 0.3);
  for (auto& u : s.velocity)
    for (Scalar& x : u) x = normal(rng);
  for (Scalar& x : s.density) x = std::fabs(normal(rng));
}

TEST(GridSolver, StateCopyResumesBitForBit) {
  for (const auto& dims : {std::vector<Index>{20, 16}, std::vector<Index>{8, 10, 12}}) {
    const GridShape shape(dims);
    const Model model = box_with_obstacle(shape);
    const Config config = smoke_config();
    Solver a(model, config);
    State s = a.make_state();
    stir(s, 5);
    Interrupt interrupt;
    for (int k = 0; k < 3; ++k) a.step(s, 0.01, interrupt);
    const State saved = s;
    for (int k = 0; k < 3; ++k) a.step(s, 0.01, interrupt);
    Solver b(model, config);
    State resumed = saved;
    for (int k = 0; k < 3; ++k) b.step(resumed, 0.01, interrupt);
    for (int axis = 0; axis < 3; ++axis) EXPECT_EQ(resumed.velocity[axis], s.velocity[axis]) << "axis " << axis;
    EXPECT_EQ(resumed.pressure, s.pressure);
    EXPECT_EQ(resumed.density, s.density);
    EXPECT_EQ(resumed.temperature, s.temperature);
    EXPECT_EQ(resumed.time, s.time);
    EXPECT_EQ(resumed.steps, s.steps);
  }
}

TEST(GridSolver, ChecksValuesWhereTheyEnter) {
  const GridShape shape(std::vector<Index>{8, 8});
  Solver solver(make_model(shape, 0.1), Config{});
  State s = solver.make_state();
  Interrupt interrupt;
  EXPECT_THROW(solver.step(s, 0, interrupt), InvalidArgument);
  EXPECT_THROW(solver.step(s, std::nan(""), interrupt), InvalidArgument);
  State wrong = s;
  wrong.pressure.resize(3);
  EXPECT_THROW(solver.step(wrong, 0.01, interrupt), InvalidArgument);
  EXPECT_THROW(make_model(shape, -1), InvalidArgument);
  Config bad;
  bad.tol = 2;
  EXPECT_THROW(Solver(make_model(shape, 0.1), bad), InvalidArgument);
  bad = Config{};
  bad.open[0] = true;  // a z side of a 2D grid
  EXPECT_THROW(Solver(make_model(shape, 0.1), bad), InvalidArgument);
}

TEST(GridSolver, FailedStepLeavesTheStateAsItWas) {
  const GridShape shape(std::vector<Index>{8, 8});
  Solver solver(make_model(shape, 0.1), Config{});
  State s = solver.make_state();
  stir(s, 2);
  s.velocity[1][5] = std::nan("");
  const State before = s;
  Interrupt interrupt;
  EXPECT_THROW(solver.step(s, 0.01, interrupt), DivergenceError);
  EXPECT_EQ(s.time, before.time);
  EXPECT_EQ(s.velocity[2], before.velocity[2]);
}

TEST(GridSolver, StableDtIsTheCflRule) {
  const GridShape shape(std::vector<Index>{16, 16});
  const Scalar h = 1.0 / 16;
  Config c;
  c.gravity[1] = -9.8;
  Solver solver(make_model(shape, h), c);
  State s = solver.make_state();
  s.velocity[2][40] = -0.7;
  const Scalar expect = 0.5 * h / (0.7 + std::sqrt(5 * h * 9.8));
  EXPECT_NEAR(solver.stable_dt(s, 0.5), expect, 1e-15);
  EXPECT_EQ(solver.stable_dt(s, 0.5, 1e-4), 1e-4);
  // advance lands on the end (core/advance.h) and counts its steps
  Interrupt interrupt;
  StepStats last;
  const Index steps = solver.advance(s, 0.05, 0.5, 1.0, interrupt, &last).steps;
  EXPECT_GE(steps, 1);
  EXPECT_EQ(s.time, 0.05);
  EXPECT_EQ(last.time, s.time);
  EXPECT_EQ(s.steps, steps);
}

}  // namespace
}  // namespace kinema::grid
