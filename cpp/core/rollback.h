// Transactional steps: a step that throws (a DivergenceError, a failed solve, Ctrl-C) leaves the
// State exactly as it was before it, so the caller can take the error's advice (a smaller dt)
// and go on. Every solver's step entry point runs through with_rollback.
#pragma once

#include <utility>

namespace kinema {

// Runs step() and returns its result; when it throws, copies the saved State back and rethrows.
// The restore is a copy assignment, not a move: std::vector reuses its buffer when the sizes
// match, so the zero-copy numpy views of the State stay valid.
template <class State, class Step>
decltype(auto) with_rollback(State& state, Step&& step) {
  const State before = state;
  try {
    return std::forward<Step>(step)();
  } catch (...) {
    state = before;
    throw;
  }
}

// The same with a caller-owned backup that keeps its buffers from call to call: copy
// assignment reuses them, so a large state costs one copy per step and no allocation (a fresh
// copy each step can land where the allocator returns memory to the system and page-faults
// back in every step).
template <class State, class Step>
decltype(auto) with_rollback(State& state, State& backup, Step&& step) {
  backup = state;
  try {
    return std::forward<Step>(step)();
  } catch (...) {
    state = backup;
    throw;
  }
}

}  // namespace kinema
