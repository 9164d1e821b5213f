"""The copies km.grid's bindings no longer make around each adjoint step: adjoint vectors moved
into the returned arrays, controls read in place, the controls' gradient returned as made. Each
must leave no array aliased to memory that is written later: these tests write into or reuse
every buffer after it was handed out and check that nothing seen before changes."""

from __future__ import annotations

import numpy as np
import pytest

import kinema as km
from test_diff_grid import _fluid


def _snapshot(d):
    return {k: np.array(v, copy=True) for k, v in d.items() if isinstance(v, np.ndarray)}


def _assert_same(d, snap):
    for k, v in snap.items():
        np.testing.assert_array_equal(d[k], v, err_msg=k)


@pytest.mark.parametrize("shape", [(12, 10), (8, 6, 7)])
def test_state_arrays_are_fresh_and_own_their_memory(shape):
    sim = _fluid(shape, "maccormack", 2)
    a = sim.state()
    snap = _snapshot(a)
    views = list(sim._state_arrays().values())
    b = sim.state()
    for name, x in a.items():
        if not isinstance(x, np.ndarray) or x.ndim == 0:
            continue
        assert x.flags.c_contiguous and x.dtype == np.float64
        for v in views:  # not the simulation's own arrays
            assert not np.shares_memory(x, v), name
        for y in b.values():  # nor another state()'s
            if isinstance(y, np.ndarray):
                assert not np.shares_memory(x, y), name
    sim._diff_step(0.02, None, {})  # the simulation moves on: what state() gave stays
    _assert_same(a, snap)
    b["u"][...] = 7.0  # writing into one state's array changes no other, nor the simulation
    _assert_same(a, snap)
    assert not np.any(sim.u == 7.0)


@pytest.mark.parametrize("shape", [(12, 10), (8, 6, 7)])
@pytest.mark.parametrize("advection", ["semi_lagrangian", "bfecc"])
def test_adjoint_step_reads_its_inputs_and_returns_new_arrays(shape, advection):
    sim = _fluid(shape, advection, 2)
    rng = np.random.default_rng(5)
    dt = 0.02 if len(shape) == 2 else 0.03
    before = sim.state()
    control = rng.normal(0, 1, sim._diff_control_shape())
    control_snap = control.copy()
    sim._diff_step(dt, control, {})
    after = sim.state()
    grads = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    grads_snap = _snapshot(grads)
    before_snap = _snapshot(before)
    gb, _, gc = sim._diff_step_adjoint(dt, before, after, control, grads, {})
    for name in sim._diff_state_names:
        assert np.any(gb[name] != 0), name
    # the inputs are read, never written
    _assert_same(before, before_snap)
    _assert_same(grads, grads_snap)
    np.testing.assert_array_equal(control, control_snap)
    # a later adjoint step does not write into the arrays an earlier one returned
    snap = _snapshot(gb)
    gc_snap = gc.copy()
    sim._diff_step_adjoint(dt, before, after, control, gb, {})
    _assert_same(gb, snap)
    np.testing.assert_array_equal(gc, gc_snap)
    for name in sim._diff_state_names:  # nor are they the inputs' memory
        assert not np.shares_memory(gb[name], grads[name]), name
        assert not np.shares_memory(gb[name], before[name]), name


@pytest.mark.parametrize("checkpoints", [None, 3])
def test_backward_results_are_not_overwritten_by_a_later_backward(checkpoints):
    sim = _fluid((12, 10), "maccormack", 2)
    rng = np.random.default_rng(2)
    steps, dt = 5, 0.02
    controls = rng.normal(0, 1, (steps,) + sim._diff_control_shape())
    wrt = sim._diff_state_names + ("controls", "viscosity")
    run = km.diff.rollout(sim, steps, dt, wrt=wrt, controls=controls, checkpoints=checkpoints)
    outputs = _snapshot(run.outputs)
    w1 = {n: rng.normal(size=run.outputs[n].shape) for n in run.outputs}
    first = run.backward(w1)
    snap = _snapshot(first)
    w2 = {n: rng.normal(size=run.outputs[n].shape) for n in run.outputs}
    second = run.backward(w2)
    _assert_same(first, snap)
    _assert_same(run.outputs, outputs)
    for name in wrt:
        if isinstance(first[name], np.ndarray):
            assert not np.shares_memory(first[name], second[name]), name
    assert np.any(first["controls"] != second["controls"])
    again = run.backward(w1)  # the same gradients again: nothing held by the run was overwritten
    for name in wrt:
        np.testing.assert_array_equal(again[name], first[name], err_msg=name)
