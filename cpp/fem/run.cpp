// A run of fem/solver.h's steps kept whole for reverse mode, and its adjoint in one call: the
// forward steps and the adjoint steps of fem/adjoint.cpp with no round trip to Python per step
// (python/kinema/diff.py's optional _diff_record path). The gradients are those of step_adjoint
// called step by step on the same states, bit for bit: the same adjoint step on the same inputs,
// and the parameter gradients summed in the order such a caller sums them.
#include <string>

#include "core/errors.h"
#include "fem/solver.h"

namespace kinema::fem {

namespace {

// sum += term element by element; an empty sum takes the term as it is (0 + t = t exactly).
void add_to(std::vector<Scalar>& sum, const std::vector<Scalar>& term) {
  if (sum.empty()) {
    sum = term;
    return;
  }
  for (std::size_t i = 0; i < term.size(); ++i) sum[i] += term[i];
}

}  // namespace

void Solver::record(State& state, Scalar dt, Index steps, const Scalar* controls, StoredRun& run,
                    Interrupt& interrupt) {
  if (steps < 0)
    throw InvalidArgument("steps: expected an integer >= 0, got " + std::to_string(steps));
  const std::size_t size = model_.rest.size();
  if (state.x.size() != size || state.v.size() != size)
    throw InvalidArgument("state: x and v must hold " + std::to_string(model_.vertex_count) +
                          " vertices of the model");
  const Index n = assembly_.dof_count();
  run.dt = dt;
  run.states.resize(static_cast<std::size_t>(steps) + 1);  // an earlier run's buffers are reused
  run.factors.clear();
  run.factor_of.assign(static_cast<std::size_t>(steps) + 1, 0);
  const auto keep = [&](Index k) {
    State& to = run.states[static_cast<std::size_t>(k)];
    to.x = state.x;  // copy assignment: reuses the buffer
    to.v = state.v;
    to.time = state.time;
    to.step = state.step;
    to.factor = FactorRecord{};
    if (run.factors.empty() || !(run.factors.back() == state.factor))
      run.factors.push_back(state.factor);
    run.factor_of[static_cast<std::size_t>(k)] = static_cast<Index>(run.factors.size()) - 1;
  };
  keep(0);
  for (Index k = 0; k < steps; ++k) {
    try {
      interrupt.check();
      step(state, dt, interrupt, controls ? controls + k * n : nullptr);
    } catch (...) {
      // Back to the last completed step (the kept state and its factor's record).
      const State& last = run.states[static_cast<std::size_t>(k)];
      state.x = last.x;
      state.v = last.v;
      state.time = last.time;
      state.step = last.step;
      state.factor = run.factors[static_cast<std::size_t>(run.factor_of[static_cast<std::size_t>(k)])];
      run.states.resize(static_cast<std::size_t>(k) + 1);
      run.factor_of.resize(static_cast<std::size_t>(k) + 1);
      throw;
    }
    keep(k + 1);
  }
}

void Solver::run_adjoint(const StoredRun& run, const Scalar* controls, State& adjoint,
                         ParameterGradient& params, Scalar* grad_controls, Interrupt& interrupt,
                         const ParameterMask& wanted) {
  const Index steps = run.steps();
  const Index n = assembly_.dof_count();
  params = ParameterGradient{};
  ParameterGradient step_params;
  for (Index k = steps - 1; k >= 0; --k) {
    const State& before = run.states[static_cast<std::size_t>(k)];
    const State& after = run.states[static_cast<std::size_t>(k) + 1];
    const FactorRecord& after_factor =
        run.factors[static_cast<std::size_t>(run.factor_of[static_cast<std::size_t>(k) + 1])];
    const FactorRecord& factor =
        after_factor.x.empty()
            ? run.factors[static_cast<std::size_t>(run.factor_of[static_cast<std::size_t>(k)])]
            : after_factor;
    adjoint_step(before, after, factor, run.dt, controls ? controls + k * n : nullptr, adjoint,
                 step_params, grad_controls ? grad_controls + k * n : nullptr, interrupt, wanted);
    add_to(params.youngs_modulus, step_params.youngs_modulus);
    add_to(params.poisson_ratio, step_params.poisson_ratio);
    params.density += step_params.density;
    params.damping += step_params.damping;
  }
}

}  // namespace kinema::fem
