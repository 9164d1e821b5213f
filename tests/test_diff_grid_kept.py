"""km.grid's adjoint reading the forward's kept advection scratch (MacCormack's and BFECC's first
pass, clamp bounds, BFECC's corrected field) instead of recomputing it: the same bits as the
recomputed adjoint, in runs stored whole (the C++ record) and checkpointed (km.diff's
_diff_step_keep), and the kept scratch is actually read."""

from __future__ import annotations

import numpy as np
import pytest

import kinema as km
from test_diff_grid import _fluid


def _recomputing(sim):
    # the adjoint without the kept scratch: every step recomputes the forward's first passes
    sim._diff_step_keep = None
    sim._diff_record = lambda dt, steps, controls, options: km.grid._Record(
        sim, sim._core.record(dt, int(steps), controls, False))


@pytest.mark.parametrize("shape,advection", [((12, 10), "maccormack"), ((12, 10), "bfecc"), ((8, 6, 7), "maccormack"),
                                             ((8, 6, 7), "bfecc")])
@pytest.mark.parametrize("checkpoints", [None, 2, 4])
def test_kept_scratch_gives_the_recomputed_gradients(shape, advection, checkpoints):
    sim = _fluid(shape, advection, 2)
    s0 = sim.state()
    rng = np.random.default_rng(11)
    steps = 7
    dt = 0.02 if len(shape) == 2 else 0.03
    controls = rng.normal(0, 1, (steps,) + sim._diff_control_shape())
    weights = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    wrt = sim._diff_state_names + ("controls",)
    read = []
    step_adjoint = type(sim)._diff_step_adjoint

    def counting(self, *args, forward=None, **kwargs):
        read.append(forward is not None)
        return step_adjoint(self, *args, forward=forward, **kwargs)

    sim._diff_step_adjoint = counting.__get__(sim)
    kept = km.diff.rollout(sim, steps, dt, wrt=wrt, controls=controls, checkpoints=checkpoints).backward(weights)
    if checkpoints is not None:
        # the rollout's last step, and the recomputed steps reversed right after their re-run
        assert sum(read) >= 2, read
    sim.set_state(s0)
    _recomputing(sim)
    plain = km.diff.rollout(sim, steps, dt, wrt=wrt, controls=controls, checkpoints=checkpoints).backward(weights)
    for name in wrt:
        assert np.any(kept[name] != 0), name
        np.testing.assert_array_equal(kept[name], plain[name], err_msg=name)


def test_step_keep_is_a_plain_step():
    sim = _fluid((12, 10), "bfecc", 2)
    s0 = sim.state()
    control = np.random.default_rng(3).normal(0, 1, sim._diff_control_shape())
    assert sim._diff_step_keep(0.02, control, {}) is not None
    after_keep = sim.state()
    sim.set_state(s0)
    sim._diff_step(0.02, control, {})
    for name, value in sim.state().items():
        np.testing.assert_array_equal(np.asarray(value), np.asarray(after_keep[name]), err_msg=name)
    semi = _fluid((12, 10), "semi_lagrangian", 1)
    assert semi._diff_step_keep(0.02, control, {}) is None  # its adjoint reads no scratch


@pytest.mark.parametrize("steps,checkpoints", [(9, 6), (7, 2), (16, 8), (20, 3)])
def test_checkpointed_run_holds_at_most_two_kept_scratch_sets(steps, checkpoints):
    # km.diff keeps the rollout's last two steps' scratch and that of re-run steps whose reversal
    # comes soon, never more than two sets at once (each is 3-4 arrays per advected field), and
    # every set it keeps is read by its step's adjoint
    sim = _fluid((8, 6, 7), "maccormack", 2)
    control = np.random.default_rng(5).normal(0, 1, (steps,) + sim._diff_control_shape())
    alive, made, read, most = set(), [], [], [0]
    keep, step_adjoint = type(sim)._diff_step_keep, type(sim)._diff_step_adjoint

    def keeping(self, *args):
        kept = keep(self, *args)
        alive.add(id(kept))
        made.append(id(kept))
        most[0] = max(most[0], len(alive))
        return kept

    def adjoint(self, *args, forward=None, **kwargs):
        if forward is not None:
            read.append(id(forward))
            alive.discard(id(forward))
        return step_adjoint(self, *args, forward=forward, **kwargs)

    sim._diff_step_keep = keeping.__get__(sim)
    sim._diff_step_adjoint = adjoint.__get__(sim)
    run = km.diff.rollout(sim, steps, 0.03, wrt=("controls",), controls=control, checkpoints=checkpoints)
    run.backward({"density": np.ones(sim.shape)})
    assert most[0] <= 2
    assert sorted(made) == sorted(read)  # none kept in vain (ids of sets refilled repeat in both)
    if (steps, checkpoints) == (9, 6):
        # the benchmark's case: Revolve re-runs steps 6, 3 and 4; the rollout keeps 7 and 8, the
        # re-runs 6, 3 and 4, so only the adjoints of 5, 2, 1 and 0 recompute their first passes
        assert len(read) == 5
