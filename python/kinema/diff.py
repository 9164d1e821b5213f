"""Gradients of whole simulation runs (reverse mode).

``rollout`` advances a simulation by a number of steps and records what the backward pass needs;
``Rollout.backward`` turns the gradient of a loss with respect to the final state into gradients
with respect to the initial state, the solver's parameters and per-step controls::

    sim = km.massspring.System(x, springs, stiffness=1e3, mass=0.1, gravity=(0, -9.81))
    run = km.diff.rollout(sim, steps=100, dt=1e-3, wrt=("v", "stiffness"))
    target = ...
    grads = run.backward({"x": 2 * (run.outputs["x"] - target)})   # L = |x_T - target|^2
    grads["v"]          # dL/dv_0, shape (n, d)
    grads["stiffness"]  # dL/dk, a float (stiffness was given as a scalar)

The gradients are those of the discrete simulation as run: each step's vector-Jacobian product is
computed by the solver's own adjoint (linear and Newton solves differentiated as if solved
exactly, by the implicit function theorem). Where the forward step switched branch (a clamp, a
limiter, a definiteness fix), the gradient is that of the branch taken; each solver's guide page
says where that happens.

Memory. By default every state of the run is stored (T + 1 states for T steps). With
``checkpoints=K`` at most K states are held (the initial one included) and the others are
recomputed from the nearest stored one by binomial checkpointing (Griewank 1992; Griewank and
Walther 2000, "Revolve", ACM TOMS 26): with s free slots and r forward sweeps,
beta(s, r) = C(s + r, s) steps can be reversed, so K = 2 sqrt(T) needs two sweeps: the rollout's
own, which leaves the first checkpoints in place, and at most T more recomputed steps in the
backward pass (a step's adjoint needs the states before and after it; the state before the step
reversed last is kept as the next one's after rather than recomputed, so at most K + 2 states are
held). The gradients equal the stored run's to rounding (bitwise, as the forward steps are
deterministic).

Chaining. A loss on intermediate states is written by splitting the run: the gradient a later
rollout returns for its initial state is the ``grads`` of the earlier one, and the parameter
gradients of consecutive rollouts add up to those of the one long rollout.

Which simulations are differentiable: a class that implements the protocol below. Its guide page
lists its parameters (``sim.parameters``) and what its adjoint covers.

The protocol (private methods; nothing else is called):

- ``parameters``: tuple of names; ``state() -> dict`` and ``set_state(dict)`` (exact).
- ``_diff_state_names``: the state() keys that are differentiable inputs and outputs.
- ``_diff_check(wrt, step_options)``: raises ValueError for what the adjoint cannot do.
- ``_diff_control_shape()``: the shape of one step's control.
- ``_diff_get(name)`` / ``_diff_set(name, value)``: a state array's or parameter's value.
- ``_diff_step(dt, control, step_options)``: ``step(dt, **step_options)`` plus the control.
- ``_diff_step_adjoint(dt, before, after, control, grad_after, step_options)
  -> (grad_before, grad_params, grad_control)``: the vector-Jacobian product of one step. A
  scalar parameter's gradient may be a float or the array of its per-item contributions
  (km.diff sums over the steps first and over the items last).

Optional (a faster path for runs stored whole; km.diff falls back to the steps without it):

- ``_diff_record(dt, steps, controls, step_options) -> record or None``: the same as ``steps``
  calls of ``_diff_step``, with every state kept by the simulation; ``record.backward(grad_after,
  params) -> (grad_before, grad_params, grad_controls)``: the steps' ``_diff_step_adjoint`` in
  sequence, last step first, grad_params for the names in ``params`` summed over the steps in
  that order (per item), grad_controls of shape (steps, *control_shape) or None.
- ``_diff_want(names or None)``: ``backward`` tells the simulation which parameters it wants
  (a tuple of names) before its adjoint steps and None (all) after them; ``_diff_step_adjoint``
  may then leave the others out of grad_params (they count as zero) and skip their cost.
- ``_diff_step_keep(dt, control, step_options) -> kept or None``: ``_diff_step`` that also
  returns what the step's adjoint would otherwise recompute of it; a checkpointed run calls it
  for the rollout's last two steps and for a recomputed step whose adjoint comes soon (at most
  two held at once) and passes it as ``_diff_step_adjoint(..., forward=kept)``. The gradients
  must not change (bitwise).
"""

from __future__ import annotations

import math
import numbers
import os

import numpy as np

from kinema._checks import as_float_array
from kinema.errors import DivergenceError

__all__ = ["rollout", "Rollout"]

_KEPT = 2  # the most _diff_step_keep results held at once

_PROTOCOL = ("parameters", "state", "set_state", "_diff_state_names", "_diff_check",
             "_diff_control_shape", "_diff_get", "_diff_set", "_diff_step", "_diff_step_adjoint")


def _beta(free: int, sweeps: int) -> int:
    """Steps reversible with `free` checkpoint slots and `sweeps` forward sweeps: C(s + r, s)."""
    return math.comb(free + sweeps, free)


def _split(length: int, free: int) -> int:
    """Where to place the next checkpoint in a segment of `length` steps (> 1) with `free` > 0
    slots: the smallest offset a >= 1 such that the right part length - a is reversible with
    free - 1 slots in the fewest sweeps r that reverse the whole segment (beta(free, r) >= length)."""
    sweeps = 1
    while _beta(free, sweeps) < length:
        sweeps += 1
    return min(max(1, length - _beta(free - 1, sweeps)), length - 1)


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    a = np.ascontiguousarray(a).reshape(-1).view(np.uint8)
    b = np.ascontiguousarray(b).reshape(-1).view(np.uint8)
    head = min(a.size, 4096)  # most arrays that changed differ at the start: no full pass then
    return np.array_equal(a[:head], b[:head]) and np.array_equal(a[head:], b[head:])


def _copy_state(state: dict, previous: dict | None = None) -> dict:
    """A copy of `state` whose arrays are new, except those bitwise equal to the same entry of
    `previous` (an earlier copy), which are shared: what did not change between two copies (a
    lagged factor's record, a static field) is held once. Held copies are never written."""
    out = {}
    for k, v in state.items():
        if not isinstance(v, np.ndarray):
            out[k] = v
            continue
        p = None if previous is None else previous.get(k)
        out[k] = p if isinstance(p, np.ndarray) and _same_bits(p, v) else np.array(v, copy=True)
    return out


def _as_names(wrt) -> tuple:
    if isinstance(wrt, str):
        return (wrt,)
    try:
        names = tuple(wrt)
    except TypeError:
        raise ValueError(f"wrt: expected a name or a sequence of names, got {type(wrt).__name__}") from None
    for name in names:
        if not isinstance(name, str):
            raise ValueError(f"wrt: expected names (str), got {name!r}")
    if not names:
        raise ValueError("wrt: expected at least one name")
    if len(set(names)) != len(names):
        raise ValueError(f"wrt: repeated names in {names}")
    return names


def _check_run(steps, dt) -> tuple:
    """(steps, dt) checked: an int >= 0 and a finite step > 0."""
    if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or not 0 <= steps <= 2**63 - 1:
        raise ValueError(f"steps: expected an int in [0, 2^63), got {steps!r}")
    try:
        if isinstance(dt, (bool, np.bool_, str, bytes)):
            raise TypeError
        dt = float(dt)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"dt: expected a finite step > 0 [s], got {dt!r:.60}") from None
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: expected a finite step > 0 [s], got {dt!r}")
    if not math.isfinite(steps * dt):
        raise ValueError(f"dt: {steps} steps of {dt} s overflow the simulated time")
    return int(steps), dt


def _memory_bytes() -> float:
    """The machine's physical memory [bytes] (inf where the system does not say)."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def rollout(sim, steps, dt, *, wrt, controls=None, checkpoints=None, **step_options) -> "Rollout":
    """Advances ``sim`` by ``steps`` calls of ``sim.step(dt, **step_options)`` (plus the per-step
    ``controls``) and returns a :class:`Rollout` whose ``backward`` gives gradients.

    Args:
        sim: a differentiable simulation (km.massspring.System, km.fem.Body, ...).
        steps: number of steps (int >= 0).
        dt: step [s] (> 0).
        wrt: names to differentiate with respect to: state names of ``sim`` (their values at the
            start of the rollout, e.g. "x", "v"), names in ``sim.parameters``, or "controls".
        controls: None or an array of shape (steps, *control_shape): per-step external forcing
            (forces [N] on particles and vertices; accelerations [m/s^2] on grid cells).
        checkpoints: None (store every state) or an int K >= 1: hold at most K states and
            recompute the rest (binomial checkpointing).
        **step_options: passed to every step (e.g. integrator="implicit").

    Raises:
        ValueError: naming the argument: an unknown ``wrt`` name, "controls" in ``wrt`` without
        ``controls``, a wrongly shaped ``controls``, or an option the adjoint cannot handle.
    """
    missing = [m for m in _PROTOCOL if not hasattr(sim, m)]
    if missing:
        raise ValueError(f"sim: a {type(sim).__name__} is not differentiable (km.diff needs "
                         f"{', '.join(missing)})")
    steps, dt = _check_run(steps, dt)
    names = _as_names(wrt)
    state_names = tuple(sim._diff_state_names)
    parameters = tuple(sim.parameters)
    known = state_names + parameters + ("controls",)
    for name in names:
        if name not in known:
            raise ValueError(f"wrt: unknown name {name!r}; expected one of {known}")
    if controls is None:
        if "controls" in names:
            raise ValueError("controls: 'controls' is in wrt but no controls were given")
    else:
        shape = (steps,) + tuple(sim._diff_control_shape())
        controls = as_float_array(controls, "controls")
        if controls.shape != shape:
            raise ValueError(f"controls: expected shape {shape}, got {controls.shape}")
    if checkpoints is not None:
        if isinstance(checkpoints, bool) or not isinstance(checkpoints, numbers.Integral) or checkpoints < 1:
            raise ValueError(f"checkpoints: expected None or an int >= 1, got {checkpoints!r}")
        checkpoints = int(checkpoints)
    if checkpoints is None or checkpoints > steps:  # every state of the run is stored
        need = (steps + 1) * sum(v.nbytes for v in sim.state().values() if isinstance(v, np.ndarray))
        if need > _memory_bytes():
            raise ValueError(f"steps: storing the {steps + 1} states of this run takes {need / 2**30:.3g} GiB, more "
                             "than this machine's memory; pass checkpoints=K (K states held, the rest recomputed)")
    step_options = dict(step_options)
    sim._diff_check(names, step_options)
    return Rollout(sim, steps, dt, names, controls, checkpoints, step_options)


class Rollout:
    """A recorded run (made by :func:`rollout`).

    Attributes:
        outputs: dict name -> array: copies of the differentiable state arrays after the run (the
            simulation itself is left in that state).
        wrt: the names ``backward`` differentiates with respect to.
        steps, dt: the run's step count and step [s].
        checkpoints: None (every state stored) or the checkpoint budget K.
        peak_states: the most states held at once by the last forward or backward pass
            (checkpoints, the initial state and the one a step is being reversed into).
        recomputed_steps: forward steps the last ``backward`` recomputed (0 when stored).
    """

    def __init__(self, sim, steps, dt, wrt, controls, checkpoints, step_options):
        self._sim = sim
        self.steps = steps
        self.dt = dt
        self.wrt = wrt
        self.checkpoints = checkpoints
        self._controls = controls
        self._options = step_options
        self._state_names = tuple(sim._diff_state_names)
        self._scalar_parameters = {
            name: np.ndim(sim._diff_get(name)) == 0 for name in sim.parameters}
        self.peak_states = 0
        self.recomputed_steps = 0
        self._held = 0
        self._last = None
        start = self._copy(sim.state())
        self._start = start
        self._record = None
        self._spine_kept = {}  # what _diff_step_keep kept of the last steps, for the first backward
        if checkpoints is None or checkpoints > steps:
            self._spine = {}
            recorder = getattr(sim, "_diff_record", None)
            if recorder is not None:
                self._record = recorder(dt, steps, controls, step_options)
            if self._record is not None:
                self._stored = None
                self._hold(steps + 1)  # held by the simulation's record
            else:
                self._stored = [start]
                self._hold(1)
                for k in range(steps):
                    self._step(k)
                    self._stored.append(self._copy(sim.state()))
                    self._hold(1)
        else:
            # Store where the first descent of the backward recursion will want checkpoints (the
            # "spine"), so the first backward call does not redo this forward sweep.
            self._stored = None
            self._spine = {}
            self._hold(1)
            offsets, i, free = [], 0, checkpoints - 1
            while self.steps - i > 1 and free > 0:
                i += _split(self.steps - i, free)
                offsets.append(i)
                free -= 1
            marks = set(offsets)
            keep = getattr(sim, "_diff_step_keep", None)
            for k in range(steps):
                if k >= steps - _KEPT and keep is not None:  # the steps reversed first
                    control = None if controls is None else controls[k]
                    kept = keep(dt, control, step_options)
                    if kept is not None:
                        self._spine_kept[k] = kept
                else:
                    self._step(k)
                if k + 1 in marks:
                    self._spine[k + 1] = self._copy(sim.state())
                    self._hold(1)
        self._end = self._copy(sim.state())
        self.outputs = {name: np.array(self._end[name], copy=True) for name in self._state_names}

    def _copy(self, state: dict) -> dict:
        self._last = _copy_state(state, self._last)
        return self._last

    # -- bookkeeping of the states held, to verify the memory bound
    def _hold(self, count: int):
        self._held += count
        self.peak_states = max(self.peak_states, self._held)

    def _step(self, k: int):
        control = None if self._controls is None else self._controls[k]
        self._sim._diff_step(self.dt, control, self._options)

    def _advance(self, state: dict, first: int, count: int, keep: bool = False) -> dict:
        """The state `count` steps after `state` (which is the state before step `first`).
        keep: the last step's adjoint comes soon; a simulation with `_diff_step_keep` then
        returns what that adjoint would recompute of the step, held until the adjoint reads it."""
        # set_state can be costly (an implicit solver rebuilds the factor its state records);
        # it is skipped when the simulation already holds `state` (it was the last one made).
        if self._current is not state:
            self._sim.set_state(state)
        last = first + count - 1
        stepper = getattr(self._sim, "_diff_step_keep", None) if keep else None
        for k in range(first, first + count):
            if k == last and stepper is not None and len(self._kept) < _KEPT:
                control = None if self._controls is None else self._controls[k]
                kept = stepper(self.dt, control, self._options)
                if kept is not None:
                    self._kept[k] = kept
            else:
                self._step(k)
            self.recomputed_steps += 1
        after = self._copy(self._sim.state())
        self._current = after
        return after

    def backward(self, grads: dict) -> dict:
        """dL/d(input) for every name in ``wrt`` from ``grads``: name -> dL/d(final value) for
        names of ``outputs`` (names left out count as zero). Returns arrays of the inputs'
        shapes (a float for a scalar parameter). May be called more than once."""
        if not isinstance(grads, dict):
            raise ValueError(f"grads: expected a dict name -> array, got {type(grads).__name__}")
        g = {}
        for name in self._state_names:
            shape = self.outputs[name].shape
            if name in grads:
                a = as_float_array(grads[name], f"grads[{name!r}]")
                if a.shape != shape:
                    raise ValueError(f"grads[{name!r}]: expected shape {shape}, got {a.shape}")
                g[name] = a.copy()
            else:
                g[name] = np.zeros(shape)
        for name in grads:
            if name not in self._state_names:
                raise ValueError(f"grads: unknown name {name!r}; expected names of the outputs "
                                 f"{self._state_names}")
        self._params = {}
        # np.zeros, not zeros_like: its pages are mapped lazily, written once by the steps
        self._grad_controls = None if self._controls is None else np.zeros(self._controls.shape)
        self.recomputed_steps = 0
        self._current = None
        # step -> what _diff_step_keep kept of it for its adjoint (at most _KEPT held)
        self._kept, self._spine_kept = self._spine_kept, {}
        if self._record is not None:
            base = self.steps + 1
        else:
            base = 1 + len(self._spine) if self._stored is None else len(self._stored)
        self._held = base
        self.peak_states = base
        wanted = tuple(name for name in self.wrt if name in self._scalar_parameters)
        want = getattr(self._sim, "_diff_want", None)  # optional: skip unwanted parameter work
        if want is not None:
            want(wanted)
        try:
            if self._record is not None:
                gb, gp, gc = self._record.backward(g, wanted)
                g = {name: gb[name] for name in self._state_names}
                self._params = dict(gp)
                if self._grad_controls is not None and gc is not None:
                    self._grad_controls[...] = gc
            elif self._stored is not None:
                for k in reversed(range(self.steps)):
                    g = self._adjoint(k, self._stored[k], self._stored[k + 1], g)
            elif self.steps > 0:
                self._hold(1)  # the final state, handed to the recursion as the last step's after
                g = self._reverse(0, self._start, self.steps, self.checkpoints - 1, g, self._end)
        except DivergenceError as exc:
            raise DivergenceError(f"grads: the backward pass overflowed ({exc}); the given gradients are "
                                  "too large for the adjoint to stay finite: scale the loss down") from None
        finally:
            if want is not None:
                want(None)
            self._kept = {}
            self._sim.set_state(self._end)
        self._spine = {}  # used up by the first backward call; later calls recompute it
        out = {}
        for name in self.wrt:
            if name == "controls":
                out[name] = self._grad_controls  # made anew by each backward call
            elif name in self._state_names:
                out[name] = g[name]
            else:
                value = self._params.get(name)
                if value is None:
                    value = 0.0 if self._scalar_parameters[name] else np.zeros(
                        np.shape(self._sim._diff_get(name)))
                out[name] = float(np.sum(value)) if self._scalar_parameters[name] else np.asarray(value)
        for name, value in out.items():
            if not np.all(np.isfinite(value)):
                raise DivergenceError(f"grads: the gradient with respect to {name!r} overflowed to a non-finite "
                                      "value; the given gradients are too large: scale the loss down")
        return out

    def _adjoint(self, k: int, before: dict, after: dict, g: dict) -> dict:
        self._current = None  # an adjoint step may leave the simulation in any state
        control = None if self._controls is None else self._controls[k]
        kept = self._kept.pop(k, None)
        extra = {} if kept is None else {"forward": kept}
        gb, gp, gc = self._sim._diff_step_adjoint(self.dt, before, after, control, g, self._options, **extra)
        for name, value in gp.items():
            self._params[name] = value if name not in self._params else self._params[name] + value
        if control is not None and gc is not None:
            self._grad_controls[k] = gc
        return {name: gb[name] for name in self._state_names}

    def _reverse(self, i: int, state_i: dict, j: int, free: int, g: dict, after=None) -> dict:
        """Reverses steps i..j-1 from the held state before step i, with `free` more slots.

        `after`: the state after step j - 1 when it is held (this call then owns it and lets it
        go), else None (it is recomputed). A step's adjoint needs the states before and after
        it; the state before the step reversed last is the state after the next one, so it is
        kept instead of recomputed: one forward step fewer per step reversed, for one more state
        held (Revolve counts the step's forward re-run into its reversal)."""
        while j > i:
            length = j - i
            if length == 1:
                if after is None:
                    after = self._advance(state_i, i, 1, keep=True)
                    self._hold(1)
                g = self._adjoint(i, state_i, after, g)
                self._held -= 1
                return g
            if free == 0:
                # No slot left: recompute the state before the last step from state_i.
                before = self._advance(state_i, i, length - 1, keep=True)  # step j - 2: reversed next
                self._hold(1)
                if after is None:
                    after = self._advance(before, j - 1, 1, keep=True)
                    self._hold(1)
                g = self._adjoint(j - 1, before, after, g)
                self._held -= 1
                after = before
                j -= 1
                continue
            m = i + _split(length, free)
            if m in self._spine:
                state_m = self._spine.pop(m)
                self._held -= 1  # moves from the spine to this recursion's slot
            else:
                # step m - 1 is reversed right after the sub-segment m..j-1; when that is one or
                # two steps, their reversal holds at most one kept result besides m - 1's
                state_m = self._advance(state_i, i, m - i, keep=j - m <= 2)
            self._hold(1)
            g = self._reverse(m, state_m, j, free - 1, g, after)
            after = state_m  # still held: the state after step m - 1, reversed next
            j = m
        return g
