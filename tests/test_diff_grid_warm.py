"""The adjoint pressure solve's warm start (Solver::projection_adjoint) must not make a gradient
depend on the order of calls. Inside one km.diff backward each step's solve starts from the
solution of the step after it, which that backward computed just before (its chain is fixed by
the run); a backward starts its chain from zero, and a lone ``_diff_step_adjoint`` call always
starts from zero. So the same adjoint evaluation gives the same bits whatever was evaluated
before it: another step's adjoint, another run's backward, or the same backward again."""

import numpy as np
import pytest

import kinema as km
from test_diff_grid import _fluid


def _steps(sim, count, dt):
    states = [sim.state()]
    for _ in range(count):
        sim._diff_step(dt, None, {})
        states.append(sim.state())
    return states


def _same(a, b, names):
    for name in names:
        np.testing.assert_array_equal(a[0][name], b[0][name], err_msg=name)
    assert a[1] == b[1]


@pytest.mark.parametrize("shape", [(12, 10), (8, 6, 7)])
def test_lone_step_adjoint_does_not_depend_on_the_call_before(shape):
    sim = _fluid(shape, "maccormack", 2)
    dt = 0.02 if len(shape) == 2 else 0.03
    s = _steps(sim, 2, dt)
    rng = np.random.default_rng(4)
    names = sim._diff_state_names
    grads = {n: rng.normal(size=getattr(sim, n).shape) for n in names}
    alone = sim._diff_step_adjoint(dt, s[0], s[1], None, grads, {})
    # the adjoint of the step after it first: before, the solve of step 0 then started from
    # step 1's solution and gave other bits
    sim._diff_step_adjoint(dt, s[1], s[2], None, grads, {})
    after_next = sim._diff_step_adjoint(dt, s[0], s[1], None, grads, {})
    _same(alone, after_next, names)
    assert any(np.any(alone[0][n] != 0) for n in names)


@pytest.mark.parametrize("checkpoints", [None, 2, "steps"])
def test_backward_does_not_depend_on_earlier_adjoint_calls(checkpoints):
    # None: the run kept whole in C++ (Fluid._diff_record); 2: checkpointed, its adjoint steps
    # through _diff_step_adjoint; "steps": every state stored by km.diff, adjoint steps in Python
    sim = _fluid((12, 10), "bfecc", 2)
    steps, dt = 4, 0.02
    rng = np.random.default_rng(5)
    controls = rng.normal(0, 1, (steps,) + sim._diff_control_shape())
    s0 = sim.state()
    if checkpoints == "steps":
        sim._diff_record = None
        checkpoints = None
    run = km.diff.rollout(sim, steps, dt, wrt=sim._diff_state_names + ("controls",), controls=controls,
                          checkpoints=checkpoints)
    w = {n: rng.normal(size=run.outputs[n].shape) for n in run.outputs}
    first = run.backward(w)
    end = sim.state()
    # lone adjoint calls of the run's own steps, then another run's backward whose last adjoint
    # is of the step from state.steps = steps (the one after the run's last step: before, the
    # run's next backward started its chain from that solution)
    sim.set_state(s0)
    states = _steps(sim, 2, dt)
    g = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    sim._diff_step_adjoint(dt, states[1], states[2], None, g, {})
    sim.set_state(end)
    later = km.diff.rollout(sim, 2, dt, wrt=("u",))
    later.backward({n: rng.normal(size=later.outputs[n].shape) for n in later.outputs})
    again = run.backward(w)
    for name, value in first.items():
        np.testing.assert_array_equal(again[name], value, err_msg=name)
