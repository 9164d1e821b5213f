"""km.diff's machinery on a NumPy simulation with a hand-written adjoint (tests/diff_toy.py):
gradients against central finite differences, binomial checkpointing equal to the stored run,
its memory bound, chaining, repeated backward passes, controls and the errors. The solvers'
own adjoints are tested in test_diff_<method>.py."""

import math

import numpy as np
import pytest

import kinema as km
from kinema import diff
from diff_toy import Oscillators

RNG = np.random.default_rng(7)


def make(n=5, d=2, stiffness=3.0, mass=1.5):
    rng = np.random.default_rng(1)
    return Oscillators(rng.normal(size=(n, d)), rng.normal(size=(n, d)), stiffness, mass)


def loss_of(x, v, w_x, w_v):
    return float((w_x * x).sum() + (w_v * v * v).sum())


def run_loss(sim, steps, dt, controls=None, **kw):
    r = diff.rollout(sim, steps, dt, wrt=("x",), controls=controls, **kw)
    return r


@pytest.mark.parametrize("name", ["x", "v", "stiffness", "mass", "cubic", "controls"])
@pytest.mark.parametrize("per_item", [False, True])
def test_gradient_matches_central_differences(name, per_item):
    steps, dt = 40, 0.02
    w_x, w_v = RNG.normal(size=(5, 2)), RNG.normal(size=(5, 2))
    k = np.linspace(2, 4, 5) if per_item else 3.0
    m = np.linspace(1, 2, 5) if per_item else 1.5
    u = 0.3 * RNG.normal(size=(steps, 5, 2))

    def loss(sim):
        return loss_of(sim.x, sim.v, w_x, w_v)

    sim = make(stiffness=k, mass=m)
    run = diff.rollout(sim, steps, dt, wrt=(name,), controls=u)
    grads = run.backward({"x": w_x, "v": 2 * w_v * run.outputs["v"]})
    g = grads[name]
    base = make(stiffness=k, mass=m)
    value = u if name == "controls" else base._diff_get(name)
    direction = RNG.normal(size=np.shape(value))
    # Central differences: error eps^2 |L'''| / 6; with eps = 1e-5 and derivatives of order 1e2
    # it is ~1e-8, far above rounding (1e-16 |L| / eps ~ 1e-11).
    eps = 1e-5

    def perturbed(sign):
        s = make(stiffness=k, mass=m)
        uu = u
        if name == "controls":
            uu = u + sign * eps * direction
        else:
            s._diff_set(name, np.asarray(s._diff_get(name)) + sign * eps * direction)
        for kk in range(steps):
            s._diff_step(dt, uu[kk], {})
        return loss(s)

    fd = (perturbed(1) - perturbed(-1)) / (2 * eps)
    ad = float(np.sum(np.asarray(g) * direction))
    assert np.shape(g) == np.shape(value)
    if name in ("stiffness", "mass") and not per_item:
        assert isinstance(g, float)
    assert abs(ad - fd) <= 1e-6 * max(1.0, abs(fd)), (name, ad, fd)


@pytest.mark.parametrize("steps,k", [(0, 1), (1, 1), (2, 1), (7, 1), (7, 2), (30, 3), (30, 11),
                                     (50, 14), (50, 51), (100, 20)])
def test_checkpointed_equals_stored_bitwise_within_the_memory_bound(steps, k):
    u = RNG.normal(size=(steps, 5, 2))
    g_out = {"x": RNG.normal(size=(5, 2)), "v": RNG.normal(size=(5, 2))}
    wrt = ("x", "v", "stiffness", "controls")
    stored = diff.rollout(make(), steps, 0.01, wrt=wrt, controls=u)
    ckpt = diff.rollout(make(), steps, 0.01, wrt=wrt, controls=u, checkpoints=k)
    a, b = stored.backward(g_out), ckpt.backward(g_out)
    for name in wrt:
        np.testing.assert_array_equal(a[name], b[name])
    for name in ("x", "v"):
        np.testing.assert_array_equal(stored.outputs[name], ckpt.outputs[name])
    if k <= steps:
        # K checkpoints plus the two transient states a reversed step is computed between.
        assert ckpt.peak_states <= k + 2, (ckpt.peak_states, k)
    assert stored.peak_states == steps + 1


def test_two_sqrt_t_checkpoints_recompute_each_step_about_once():
    steps = 400
    k = int(2 * math.sqrt(steps))
    run = diff.rollout(make(), steps, 0.01, wrt=("x",), checkpoints=k)
    run.backward({"x": np.ones((5, 2))})
    # beta(k - 1, 2) = C(k + 1, 2) >= steps: two sweeps suffice, the first made by the rollout
    # (the spine). Revolve's optimum for r = 2 sweeps, 2 T - beta(k, 1) forward steps, counts
    # each step's re-run before its reversal; km.diff keeps the state before the step reversed
    # last as the next one's after, so T of those are saved: at most T - k recomputed steps.
    assert math.comb(k + 1, 2) >= steps
    assert run.recomputed_steps <= steps - k, run.recomputed_steps
    assert run.peak_states < 3 * math.sqrt(steps)


def test_backward_twice_gives_the_same_and_leaves_the_final_state():
    sim = make()
    run = diff.rollout(sim, 25, 0.02, wrt=("v", "mass"), checkpoints=4)
    end = sim.state()
    g = {"x": np.ones((5, 2))}
    a, b = run.backward(g), run.backward(g)
    np.testing.assert_array_equal(a["v"], b["v"])
    assert a["mass"] == b["mass"]
    np.testing.assert_array_equal(sim.x, end["x"])
    np.testing.assert_array_equal(sim.v, end["v"])


def test_outputs_equal_plain_steps_bitwise():
    sim, plain = make(), make()
    run = diff.rollout(sim, 33, 0.01, wrt=("x",), checkpoints=5)
    for _ in range(33):
        plain.step(0.01)
    np.testing.assert_array_equal(run.outputs["x"], plain.x)
    np.testing.assert_array_equal(run.outputs["v"], plain.v)


def test_chained_rollouts_equal_one_rollout():
    g_out = {"x": RNG.normal(size=(5, 2)), "v": RNG.normal(size=(5, 2))}
    one = diff.rollout(make(), 30, 0.01, wrt=("x", "v", "stiffness")).backward(g_out)
    sim = make()
    first = diff.rollout(sim, 12, 0.01, wrt=("x", "v", "stiffness"))
    second = diff.rollout(sim, 18, 0.01, wrt=("x", "v", "stiffness"), checkpoints=3)
    g2 = second.backward(g_out)
    g1 = first.backward({"x": g2["x"], "v": g2["v"]})
    np.testing.assert_allclose(g1["x"], one["x"], rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(g1["v"], one["v"], rtol=1e-13, atol=1e-13)
    assert g1["stiffness"] + g2["stiffness"] == pytest.approx(one["stiffness"], rel=1e-12)


def test_energy_gradient_of_a_harmonic_oscillator_matches_theory():
    # For the harmonic oscillator (c = 0) symplectic Euler conserves the modified energy
    # H~ = m v^2 / 2 + k x^2 / 2 - dt k x v / 2 exactly (a conserved quantity of the discrete
    # map), so dH~(T)/d(x0, v0) = dH~(0)/d(x0, v0) = (k x0 - dt k v0 / 2, m v0 - dt k x0 / 2).
    dt, k, m = 0.05, 3.0, 1.5
    sim = Oscillators(RNG.normal(size=(4, 1)), RNG.normal(size=(4, 1)), k, m, 0.0)
    x0, v0 = sim.x.copy(), sim.v.copy()
    run = diff.rollout(sim, 200, dt, wrt=("x", "v"))
    x, v = run.outputs["x"], run.outputs["v"]
    g = run.backward({"x": k * x - dt * k * v / 2, "v": m * v - dt * k * x / 2})
    np.testing.assert_allclose(g["x"], k * x0 - dt * k * v0 / 2, rtol=1e-10)
    np.testing.assert_allclose(g["v"], m * v0 - dt * k * x0 / 2, rtol=1e-10)


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="wrt: unknown name 'q'"):
        diff.rollout(make(), 3, 0.1, wrt=("q",))
    with pytest.raises(ValueError, match="controls: 'controls' is in wrt"):
        diff.rollout(make(), 3, 0.1, wrt=("controls",))
    with pytest.raises(ValueError, match=r"controls: expected shape \(3, 5, 2\)"):
        diff.rollout(make(), 3, 0.1, wrt=("x",), controls=np.zeros((3, 5, 3)))
    with pytest.raises(ValueError, match=r"controls: contains .*NaN"):
        diff.rollout(make(), 1, 0.1, wrt=("x",), controls=np.full((1, 5, 2), np.nan))
    with pytest.raises(ValueError, match="checkpoints"):
        diff.rollout(make(), 3, 0.1, wrt=("x",), checkpoints=0)
    with pytest.raises(ValueError, match="steps"):
        diff.rollout(make(), -1, 0.1, wrt=("x",))
    with pytest.raises(ValueError, match="dt"):
        diff.rollout(make(), 3, float("nan"), wrt=("x",))
    with pytest.raises(ValueError, match="wrt: expected at least one"):
        diff.rollout(make(), 3, 0.1, wrt=())
    with pytest.raises(ValueError, match="integrator"):
        diff.rollout(make(), 3, 0.1, wrt=("x",), integrator="implicit")
    with pytest.raises(ValueError, match="sim: a object is not differentiable"):
        diff.rollout(object(), 3, 0.1, wrt=("x",))
    run = diff.rollout(make(), 3, 0.1, wrt=("x",))
    with pytest.raises(ValueError, match=r"grads\['x'\]: expected shape \(5, 2\)"):
        run.backward({"x": np.zeros(3)})
    with pytest.raises(ValueError, match="grads: unknown name 'w'"):
        run.backward({"w": np.zeros((5, 2))})
    with pytest.raises(ValueError, match=r"grads\['v'\]: contains .*NaN"):
        run.backward({"v": np.full((5, 2), np.inf)})


def test_is_exported():
    assert km.diff is diff


@pytest.mark.parametrize("module", ["grid", "massspring"])
def test_gradients_too_large_for_the_adjoint_name_grads(module):
    """Finite but huge output gradients make the adjoint overflow: a DivergenceError naming grads
    (never a bare solver message, never inf in the result); ordinary ones still work after it."""
    if module == "grid":
        sim = km.grid.Fluid((16, 16), 1 / 16, density=True)
        sim.density[4:8, 4:8] = 1.0
        run = km.diff.rollout(sim, 3, 0.01, wrt=("density",))
        name, shape = "density", sim.density.shape
    else:
        x = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
        sim = km.massspring.System(x, np.array([[0, 1], [1, 2]]), stiffness=10.0, mass=1.0)
        # dL/dv0 = (steps * dt) dL/dx for a uniform translation: 3 x 1e308 overflows
        run = km.diff.rollout(sim, 300, 1e-2, wrt=("v",), integrator="symplectic")
        name, shape = "x", sim.x.shape
    with pytest.raises(km.DivergenceError, match="grads"):
        run.backward({name: np.full(shape, 1e308)})
    g = run.backward({name: np.ones(shape)})
    assert all(np.all(np.isfinite(v)) for v in g.values())
