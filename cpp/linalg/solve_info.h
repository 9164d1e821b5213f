// Statistics of an iterative solve (Python: km.SolveInfo).
#pragma once

#include <vector>

#include "core/types.h"

namespace kinema {

struct SolveInfo {
  Index iterations = 0;
  Scalar residual = 0;           // relative 2-norm ||b - A x|| / ||b||
  bool converged = false;
  std::vector<Scalar> history;   // residual after each iteration, history[0] at the start
  double seconds = 0;
};

// Stopping rule shared by the iterative solvers.
struct IterativeOptions {
  Scalar tol = 1e-8;             // on the relative residual
  Index max_iter = 0;            // 0: the solver's default for the problem size
};

}  // namespace kinema
