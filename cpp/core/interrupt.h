// Cooperative cancellation for long computations. The core cannot see Python, so the caller
// hands in a poll function (the bindings' one checks for Ctrl-C under the GIL). Solvers call
// check() between iterations, never inside a parallel region; polls are rate-limited so that
// checking every iteration costs nothing measurable.
#pragma once

#include <chrono>
#include <functional>
#include <utility>

#include "core/errors.h"

namespace kinema {

class Interrupt {
 public:
  using Poll = std::function<bool()>;  // returns true when the computation must stop

  Interrupt() = default;
  explicit Interrupt(Poll poll, double interval_seconds = 0.1)
      : poll_(std::move(poll)), interval_(interval_seconds), last_(Clock::now()) {}

  // Throws Interrupted when the poll function asks to stop.
  void check() {
    if (requested()) throw Interrupted();
  }

  // Whether the poll function asked to stop, without throwing: for the one thread of a parallel
  // region that polls (an exception must not leave the region), which then tells the others to
  // skip their remaining work; check() after the region throws. The answer is sticky.
  bool requested() {
    if (stopped_ || !poll_) return stopped_;
    const auto now = Clock::now();
    if (std::chrono::duration<double>(now - last_).count() < interval_) return false;
    last_ = now;
    stopped_ = poll_();
    return stopped_;
  }

 private:
  using Clock = std::chrono::steady_clock;
  Poll poll_;
  double interval_ = 0.1;
  Clock::time_point last_{};
  bool stopped_ = false;
};

}  // namespace kinema
