// The SPH solver's shape: Solver(model, config) and step(State&, dt, Interrupt&) with
// everything a step reads from the earlier ones in the State, so that a copy of the State
// resumes bit for bit (on the same solver and on a second one), for both methods in 2D and 3D;
// config values are checked where they enter (make_model, the Solver).
#include <gtest/gtest.h>

#include <vector>

#include "core/errors.h"
#include "core/interrupt.h"
#include "sph/solver.h"

namespace kinema {

namespace {

// A column collapsing in a closed tank, advanced `steps` CFL steps.
struct Column {
  Column(int d, sph::Method method) : state(d, 0) {
    const Scalar lower[3] = {0, 0, 0}, column[3] = {0.1, 0.2, 0.06}, box[3] = {0.3, 0.3, 0.06};
    const Scalar s = d == 2 ? 0.01 : 0.02;
    const std::vector<Scalar> x = sph::block(d, lower, column, s);
    state = sph::State(d, static_cast<Index>(x.size()) / d);
    state.x = x;
    config.method = method;
    config.gravity = {0, -9.81, 0};
    config.viscosity = 1e-3;
    config.reorder_every = 3;
    model = sph::make_model(config, state, s, {}, lower, box);
  }
  sph::State state;
  sph::Config config;
  sph::Model model;
};

std::vector<sph::StepStats> run(sph::Solver& solver, sph::State& s, int steps) {
  Interrupt interrupt;
  std::vector<sph::StepStats> out;
  for (int k = 0; k < steps; ++k) out.push_back(solver.step(s, solver.stable_dt(s, 0.4), interrupt));
  return out;
}

void expect_copy_resumes(int d, sph::Method method) {
  Column c(d, method);
  sph::Solver solver(c.model, c.config);
  // WCSPH's acoustic steps are short: more of them, so that the column moves and the lists of
  // the continued run are rebuilt.
  const int steps = method == sph::Method::WCSPH ? 200 : 30;
  run(solver, c.state, steps);
  const sph::State saved = c.state;
  const auto straight = run(solver, c.state, steps);
  bool rebuilt = false;
  for (const auto& st : straight) rebuilt |= st.neighbor_rebuild;
  EXPECT_TRUE(rebuilt);
  sph::Solver other(c.model, c.config);
  for (sph::Solver* s : {&solver, &other}) {
    sph::State resumed = saved;
    const auto again = run(*s, resumed, steps);
    for (size_t k = 0; k < again.size(); ++k) {
      EXPECT_EQ(again[k].iterations, straight[k].iterations) << "step " << k;
      EXPECT_EQ(again[k].neighbor_rebuild, straight[k].neighbor_rebuild) << "step " << k;
    }
    EXPECT_EQ(resumed.x, c.state.x);
    EXPECT_EQ(resumed.v, c.state.v);
    EXPECT_EQ(resumed.pressure, c.state.pressure);
    EXPECT_EQ(resumed.ids, c.state.ids);
    EXPECT_EQ(resumed.time, c.state.time);
  }
}

}  // namespace

TEST(SphSolver, CopyOfStateResumesBitwise2D) {
  expect_copy_resumes(2, sph::Method::DFSPH);
  expect_copy_resumes(2, sph::Method::WCSPH);
}

TEST(SphSolver, CopyOfStateResumesBitwise3D) {
  expect_copy_resumes(3, sph::Method::DFSPH);
  expect_copy_resumes(3, sph::Method::WCSPH);
}

TEST(SphSolver, ConfigIsCheckedWhereItEnters) {
  Column c(2, sph::Method::DFSPH);
  sph::Config bad = c.config;
  bad.tol = 0;
  EXPECT_THROW(sph::Solver(c.model, bad), InvalidArgument);
  EXPECT_THROW(sph::make_model(bad, c.state, 0.01, {}, nullptr, nullptr), InvalidArgument);
  sph::Solver solver(c.model, c.config);
  Interrupt interrupt;
  EXPECT_THROW(solver.step(c.state, -1, interrupt), InvalidArgument);
  sph::State other(3, 4);
  EXPECT_THROW(solver.step(other, 1e-3, interrupt), InvalidArgument);
}

}  // namespace kinema
