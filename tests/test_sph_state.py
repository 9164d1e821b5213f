"""km.sph.Fluid.state() / set_state(): a run resumed from a state is bitwise the run that was not
stopped, across DFSPH's warm start, a Verlet-list rebuild, a Morton reordering and a change of
dt; bad dicts are refused without changing anything; the stats and config objects."""

import numpy as np
import pytest

import kinema as km

G = 9.81


def column(method, d, **kw):
    s = 0.01 if d == 2 else 0.02
    size = [0.1, 0.2] + [0.1] * (d - 2)
    box = [0.4, 0.3] + [0.1] * (d - 2)
    return km.sph.Fluid(km.sph.block([0] * d, size, s), s, method=method, gravity=(0, -G, 0)[:d],
                        domain=([0] * d, box), viscosity=1e-3, reorder_every=3, **kw)


def history(fluid, steps):
    """Steps of the CFL dt (it changes from step to step); the stats that tell the paths taken."""
    out = []
    for _ in range(steps):
        st = fluid.step(fluid.stable_dt())
        out.append((st.iterations, st.divergence_iterations, st.neighbor_rebuild, st.neighbor_count, st.dt))
    return out


def assert_same(a, b, where):
    for name in ("x", "v", "density", "pressure", "ids"):
        x, y = getattr(a, name), getattr(b, name)
        assert np.array_equal(x, y), f"{where}: {name} differs by {np.abs(x - y).max():.3e}"
    assert a.time == b.time and a.steps == b.steps, where


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_resumed_run_is_bitwise_the_run_not_stopped(method, d):
    fluid = column(method, d)
    fluid.advance(0.05)  # collapsing: lists rebuilt and reordered, DFSPH's stiffnesses warm
    history(fluid, 3)
    state = fluid.state()
    # What makes the resume non-trivial: a step would not reproduce these from x and v alone.
    assert state["last_dt"] > 0 and state["reorder_step"] >= 0 and len(state["neighbor_x"]) == fluid.n
    if method == "dfsph":
        assert np.abs(state["kappa_density"]).max() > 0  # the next solve starts warm
    else:  # small steps: the lists outlive steps, so they are not those of the current positions
        assert state["neighbor_skin"] > 0
    straight = history(fluid, 25)
    assert any(h[2] for h in straight), "no neighbour rebuild in the continued run"
    if method == "wcsph":
        assert not all(h[2] for h in straight), "the Verlet lists never outlived a step"
    assert len({h[4] for h in straight}) > 1, "dt did not change"
    fluid.advance(0.01)

    for target in ("fresh", "same"):  # a new Fluid built alike, and the original one rewound
        other = column(method, d) if target == "fresh" else fluid
        other.set_state(state)
        assert history(other, 25) == straight, target
        other.advance(0.01)
        if target == "fresh":
            assert_same(fluid, other, target)
            final = {k: v.copy() for k, v in fluid.state().items()}
    for k, v in fluid.state().items():
        assert np.array_equal(v, final[k]), k


def test_state_is_a_copy_and_round_trips():
    fluid = column("dfsph", 2)
    fluid.advance(0.02)
    state = fluid.state()
    x0 = state["x"].copy()
    fluid.x[:] += 1.0
    assert np.array_equal(state["x"], x0)  # a copy, not a view
    fluid.set_state(state)
    again = fluid.state()
    assert set(again) == set(state)
    for k in state:
        assert np.array_equal(again[k], state[k]), k
    # Before the first step there are no lists: neighbor_x has no rows, and restoring that works.
    new = column("wcsph", 2)
    s0 = new.state()
    assert s0["neighbor_x"].shape == (0, 2) and "kappa_density" not in s0
    new.step(1e-4)
    new.set_state(s0)
    assert new.time == 0 and new.steps == 0


@pytest.mark.parametrize("change, match", [
    (lambda s: s.pop("kappa_density"), "kappa_density"),
    (lambda s: s.update(x=s["x"][:-1]), "x"),
    (lambda s: s.update(neighbor_x=np.zeros((3, 2))), "neighbor_x"),
    (lambda s: s.update(neighbor_skin=2.0), "neighbor_skin"),
    (lambda s: s.update(last_dt=-1.0), "last_dt"),
    (lambda s: s.update(time=np.nan), "time"),
    (lambda s: s.update(steps=2.5), "steps"),
    (lambda s: s.update(v=np.full_like(s["v"], np.nan)), "v"),
])
def test_set_state_refuses_bad_dicts_and_changes_nothing(change, match):
    fluid = column("dfsph", 2)
    fluid.advance(0.02)
    before = fluid.state()
    bad = fluid.state()
    change(bad)
    with pytest.raises(ValueError, match=match):
        fluid.set_state(bad)
    after = fluid.state()
    for k in before:
        assert np.array_equal(before[k], after[k]), k
    with pytest.raises(ValueError, match="state"):
        fluid.set_state([1, 2])


def test_step_stats_and_config_are_objects():
    fluid = column("dfsph", 2, tol=5e-4)
    st = fluid.step(1e-3)
    assert isinstance(st, km._core.sph.StepStats) and isinstance(st, km._core.StepStats)
    assert st.dt == 1e-3 and st.time == pytest.approx(1e-3) and st.seconds > 0
    assert st.iterations >= 2 and st.density_error <= 5e-4 and st.neighbor_rebuild
    config = fluid.config
    assert config.tol == 5e-4 and config.method == km._core.sph.Method.DFSPH and fluid.method == "dfsph"
    assert list(config.gravity) == [0, -G, 0] and fluid.viscosity == 1e-3
    assert km.sph.Fluid([[0.5, 0.5]], 0.01).config.gravity == [0, 0, 0]  # gravity=None: none
    assert fluid.parameters == ("viscosity",)
    with pytest.raises(AttributeError):
        st.iterations = 3
