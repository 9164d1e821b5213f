"""The copies km.diff and km.grid's bindings no longer make around each adjoint step: state()
arrays held as made (views of one C++ copy, read in place by the adjoint), adjoint vectors moved
into the returned arrays, controls read in place, the controls' gradient returned as made. Each
must leave no array aliased to memory that is written later: these tests write into or reuse
every buffer after it was handed out and check that nothing seen before changes, and that the
in-place read gives the bits of the copying one."""

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
    # views of one C++ copy of the state (the adjoint reads such a dict in place)
    assert {type(x.base) for x in a.values() if isinstance(x, np.ndarray) and x.ndim} == {km._core.grid.HeldState}
    sim._diff_step(0.02, None, {})  # the simulation moves on: what state() gave stays
    _assert_same(a, snap)
    b["u"][...] = 7.0  # writing into one state's array changes no other, nor the simulation
    _assert_same(a, snap)
    assert not np.any(sim.u == 7.0)


@pytest.mark.parametrize("shape", [(12, 10), (8, 6, 7)])
@pytest.mark.parametrize("advection", ["semi_lagrangian", "bfecc"])
def test_adjoint_reads_a_state_dict_in_place_with_the_copied_bits(shape, advection):
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
    # in place (views of a C++ copy) and copied (plain arrays, a dict the bindings cannot read in place)
    gb, gp, gc = sim._diff_step_adjoint(dt, before, after, control, grads, {})
    plain = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else v) for k, v in before.items()}
    gb2, gp2, gc2 = sim._diff_step_adjoint(dt, plain, after, control, grads, {})
    for name in sim._diff_state_names:
        assert np.any(gb[name] != 0), name
        np.testing.assert_array_equal(gb[name], gb2[name], err_msg=name)
    np.testing.assert_array_equal(gc, gc2)
    assert gp["viscosity"] == gp2["viscosity"]
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


def test_a_state_dict_changed_in_place_or_mixed_is_read_as_given():
    # the in-place read must see what the dict holds: an array written into, replaced by another
    # state's, or a different time all give the bits of the same values copied
    sim = _fluid((8, 6, 7), "maccormack", 2)
    rng = np.random.default_rng(9)
    dt = 0.03
    s0 = sim.state()
    sim._diff_step(dt, None, {})
    s1 = sim.state()
    grads = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    mixed = dict(s0, v=s1["v"])
    written = sim.state()
    written["w"] += 0.01
    for before in (mixed, written, dict(s0, time=s0["time"] + 1.0)):
        plain = {k: (np.array(v, copy=True) if isinstance(v, np.ndarray) else v) for k, v in before.items()}
        a = sim._diff_step_adjoint(dt, before, s1, None, grads, {})[0]
        b = sim._diff_step_adjoint(dt, plain, s1, None, grads, {})[0]
        for name in sim._diff_state_names:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


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
