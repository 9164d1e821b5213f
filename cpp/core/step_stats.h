// The fields every method's step statistics share. Each method's `StepStats` derives from this
// and adds its own fields beside it (iterations, residuals, per-phase seconds), so that
// `stats.time`, `stats.dt` and `stats.seconds` read the same in every module, in C++ and in
// Python (the bindings register this base once; see bindings/module.cpp).
#pragma once

#include "core/types.h"

namespace kinema {

struct StepStatsBase {
  Scalar time = 0;     // simulated time at the end of the step [s]
  Scalar dt = 0;       // the step taken [s]
  double seconds = 0;  // wall time of the step [s]
};

}  // namespace kinema
