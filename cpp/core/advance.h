// "Advance the state by a duration" once for every method: steps of the method's stable dt
// (its CFL rule) until state.time reaches the end, checking for Ctrl-C between steps.
// The last step lands exactly on the end. When what is left after a full step would be a
// sliver (less than a tenth of the step), the step is stretched to the end instead: a step
// ten per cent above the CFL dt is well inside every method's stability margin (the CFL
// numbers are fractions of the limit), whereas a sliver step costs a whole step of work for
// nothing and, in pressure solvers, a poorly conditioned solve.
#pragma once

#include <cmath>
#include <string>

#include "core/errors.h"
#include "core/interrupt.h"
#include "core/types.h"

namespace kinema {

struct AdvanceResult {
  Index steps = 0;
};

// stable_dt(state) -> Scalar > 0; step(state, dt) advances state by dt and its time with it;
// on_step(stats) (optional) sees each step's return value.
template <class State, class StableDt, class Step, class OnStep>
AdvanceResult advance_to(State& state, Scalar duration, StableDt&& stable_dt, Step&& step,
                         OnStep&& on_step, Interrupt& interrupt) {
  if (!(std::isfinite(duration) && duration >= 0))
    throw InvalidArgument("duration: expected a finite time >= 0 [s], got " + format_real(duration));
  AdvanceResult result;
  const Scalar end = state.time + duration;
  while (state.time < end) {
    interrupt.check();
    Scalar dt = stable_dt(state);
    if (!(std::isfinite(dt) && dt > 0))
      throw DivergenceError("advance: the stable time step is " + format_real(dt) +
                            " s at time " + format_real(state.time) + " s");
    const Scalar remaining = end - state.time;
    const bool last = dt >= remaining || remaining - dt < 0.1 * dt;
    if (last) dt = remaining;
    on_step(step(state, dt));
    ++result.steps;
    if (last) state.time = end;  // no round-off drift past or short of the end
  }
  return result;
}

template <class State, class StableDt, class Step>
AdvanceResult advance_to(State& state, Scalar duration, StableDt&& stable_dt, Step&& step,
                         Interrupt& interrupt) {
  return advance_to(state, duration, stable_dt, step, [](const auto&) {}, interrupt);
}

}  // namespace kinema
