// Exceptions thrown by the C++ core. The bindings map each to the Python class of the same
// role (API.md, "Errors"); the core itself never prints, exits or returns failure codes.
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>

#include "core/types.h"

namespace kinema {

// A real number for an error message, to 3 significant digits.
inline std::string format_real(Scalar v) {
  std::ostringstream s;
  s.precision(3);
  s << v;
  return s.str();
}

// Base of every kinema error (Python: km.KinemaError, a RuntimeError).
struct KinemaError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// A bad argument (Python: ValueError). The message names the argument and what was expected.
struct InvalidArgument : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};

// A non-finite value or blow-up (Python: km.DivergenceError).
struct DivergenceError : KinemaError {
  using KinemaError::KinemaError;
};

// An iterative solve reached max_iter before tol (Python: km.ConvergenceError).
struct ConvergenceError : KinemaError {
  using KinemaError::KinemaError;
};

// An explicit scheme asked beyond its stability limit (Python: km.StabilityError).
struct StabilityError : KinemaError {
  using KinemaError::KinemaError;
};

// A Cholesky factorisation met a non-positive pivot (Python: km.NotPositiveDefiniteError).
struct NotPositiveDefinite : KinemaError {
  NotPositiveDefinite(const std::string& what, Index column_)
      : KinemaError(what), column(column_) {}
  Index column;  // zero-based column where the factorisation failed
};

// The user asked to stop (Ctrl-C); the bindings turn it back into KeyboardInterrupt.
struct Interrupted : KinemaError {
  Interrupted() : KinemaError("interrupted") {}
};

}  // namespace kinema
