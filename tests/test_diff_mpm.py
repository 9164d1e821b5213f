"""Gradients of km.mpm (Solver::step_adjoint and km.diff rollouts) against central finite
differences, in 2D and 3D, for every differentiable input (x, v, F, C), parameter
(youngs_modulus, poisson_ratio per particle) and the per-step particle forces, with the
elastic materials and water, and each wall condition, Coulomb friction and a collider.

Tolerance of a check along a random direction r with step e: the central difference
D(e) = (L(p + e r) - L(p - e r)) / 2e has a truncation error c e^2 + O(e^4) and a rounding error
at most 2 delta / 2e, where delta bounds the rounding of one evaluation of L = <W, state>:
each state entry after a step is a sum of at most 27^2 products accumulated in float64, so its
relative error is below 1e3 u (u = 2^-53), and |delta| <= 1e3 u sum |W| |state|. The truncation
is measured, not guessed: D(e) - D(2e) = -3 c e^2 + O(e^4), so |D(2e) - D(e)| bounds it three
times over. A check passes when |adjoint - D(e)| <= |D(2e) - D(e)| + 2 delta / e.
"""

import numpy as np
import pytest

import kinema as km
from gradcheck import check_directional, step_adjoint_at_thread_counts

NAMES = ("x", "v", "F", "C")


def _scene(d, material, boundary="slip", friction=0.0, collider=False, seed=0, n=16):
    """A perturbed block of elastic particles moving towards the floor, with gravity, random
    F, C and per-particle moduli; near enough to the floor (and the collider) that the wall and
    contact conditions act in the steps tested."""
    rng = np.random.default_rng(seed)
    sim = km.mpm.Simulation((n,) * d, 1.0 / n, gravity=[0.0, -9.81, 0.0][:d], boundary=boundary,
                            friction=friction)
    if collider:
        sim.add_collider({"shape": "sphere", "center": [0.45] + [0.2] * (d - 1), "radius": 0.1},
                         boundary="slip", friction=friction)
    lo = np.array([0.3] + [0.02] * (d - 1))
    x = km.mpm.block(lo, lo + 0.2 if d == 2 else lo + 0.15, 1 / 40)
    x += rng.uniform(-0.004, 0.004, x.shape)
    x[:, 1] = np.maximum(x[:, 1], 0.002)
    v = rng.normal(0, 0.3, x.shape)
    v[:, 1] -= 0.5
    sim.add_particles(x, material, density=1000.0, youngs_modulus=2e3, poisson_ratio=0.3, velocity=v)
    sim.F[...] += rng.normal(0, 0.05, sim.F.shape)
    sim.C[...] += rng.normal(0, 0.5, sim.C.shape)
    sim.youngs_modulus[...] *= rng.uniform(0.8, 1.2, sim.count)
    sim.poisson_ratio[...] += rng.uniform(-0.05, 0.05, sim.count)
    return sim


# Finite-difference steps: small against each input's scale and, for x, far below the cell
# (h = 1/16) so that a perturbation rarely moves a particle across a B-spline cell boundary.
STEPS = {"x": 1e-6, "v": 1e-5, "F": 1e-5, "C": 1e-4, "youngs_modulus": 1.0, "poisson_ratio": 1e-5,
         "controls": 1e-5}


def _run(sim, s0, dt, controls, steps, override=None):
    sim.set_state(s0)
    for name, value in (override or {}).items():
        getattr(sim, name)[...] = value
    for k in range(steps):
        sim._diff_step(dt, None if controls is None else controls[k], {})
    return {k: getattr(sim, k).copy() for k in NAMES}


_fd_check = check_directional  # the bound of the module docstring, informative below 1e-3 |D|


def _check_run(sim, steps, dt, with_controls, wrt, seed, where):
    rng = np.random.default_rng(seed + 100)
    d = sim.dim
    controls = rng.normal(0, 2e-3, (steps, sim.count, d)) if with_controls else None
    s0 = sim.state()
    W = {k: rng.normal(size=s0[k].shape) for k in NAMES}
    if steps == 1:
        # The one-step adjoint as km.diff calls it.
        sim.set_state(s0)
        sim._diff_step(dt, None if controls is None else controls[0], {})
        s1 = sim.state()
        gb, gp, gc = sim._diff_step_adjoint(dt, s0, s1, None if controls is None else controls[0], W, {})
        grads = dict(gb, **gp)
        if controls is not None:
            grads["controls"] = gc[None]
    else:
        run = km.diff.rollout(sim, steps, dt, wrt=wrt, controls=controls)
        grads = run.backward(W)

    def loss_of(name):
        def loss(value):
            if name == "controls":
                out = _run(sim, s0, dt, value, steps)
            else:
                out = _run(sim, s0, dt, controls, steps, {name: value})
            terms = [W[k] * out[k] for k in NAMES]
            return float(sum(t.sum() for t in terms)), float(sum(np.abs(t).sum() for t in terms))
        return loss

    for name in wrt:
        base = controls if name == "controls" else s0[name]
        direction = rng.normal(size=base.shape)
        _fd_check(loss_of(name), base, direction, grads[name], STEPS[name], f"{where}, d/d{name}")


ALL = NAMES + ("youngs_modulus", "poisson_ratio", "controls")


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("material", ["elastic", "neohookean", "water"])
def test_one_step_adjoint_matches_central_differences(d, material):
    sim = _scene(d, material)
    # Water's stress has no Poisson ratio (its gradient is exactly 0).
    wrt = tuple(n for n in ALL if not (material == "water" and n == "poisson_ratio"))
    _check_run(sim, 1, 2e-3, True, wrt, seed=d, where=f"{d}D {material}, one step")
    if material == "water":
        sim.set_state(sim.state())
        run = km.diff.rollout(sim, 1, 2e-3, wrt=("poisson_ratio",))
        assert not run.backward({"x": np.ones_like(sim.x)})["poisson_ratio"].any()


def test_water_rollout_gradients_match_central_differences():
    sim = _scene(2, "water", boundary="slip", seed=6)
    _check_run(sim, 5, 1e-3, True, NAMES + ("youngs_modulus", "controls"), seed=12, where="2D water, five steps")


@pytest.mark.parametrize("boundary,friction,collider", [
    ("sticky", 0.0, False), ("slip", 0.0, False), ("separate", 0.0, False), ("slip", 0.4, False),
    ("separate", 0.4, True)])
def test_one_step_adjoint_through_walls_friction_and_colliders(boundary, friction, collider):
    sim = _scene(2, "elastic", boundary, friction, collider, seed=3)
    _check_run(sim, 1, 2e-3, True, ALL, seed=7, where=f"2D {boundary} friction {friction} collider {collider}")


@pytest.mark.parametrize("d", [2, 3])
def test_rollout_gradients_match_central_differences(d):
    sim = _scene(d, "neohookean" if d == 3 else "elastic", boundary="separate", friction=0.3, seed=5)
    _check_run(sim, 5, 1e-3, True, ALL, seed=11, where=f"{d}D five-step rollout")


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
def test_longer_rollout_gradients_match_central_differences(d):
    # Slip walls and a frictionless collider: their projections are linear, so no kink of the
    # separate condition or of Coulomb sticking falls inside a difference interval over 40 steps.
    sim = _scene(d, "elastic", boundary="slip", collider=True, seed=9)
    _check_run(sim, 40, 1e-3, True, ALL, seed=13, where=f"{d}D forty-step rollout")


def test_checkpointed_rollout_equals_stored_bitwise_and_outputs_equal_plain_steps():
    sim = _scene(2, "elastic", boundary="sticky", seed=2)
    s0 = sim.state()
    rng = np.random.default_rng(4)
    controls = rng.normal(0, 1e-3, (12, sim.count, 2))
    W = {"x": rng.normal(size=sim.x.shape), "F": rng.normal(size=sim.F.shape)}
    stored = km.diff.rollout(sim, 12, 1e-3, wrt=ALL, controls=controls)
    g_stored = stored.backward(W)
    sim.set_state(s0)
    ck = km.diff.rollout(sim, 12, 1e-3, wrt=ALL, controls=controls, checkpoints=3)
    g_ck = ck.backward(W)
    for k in ALL:
        assert np.array_equal(g_stored[k], g_ck[k]), f"checkpointed d/d{k} differs from the stored run's"
    assert ck.recomputed_steps > 0
    sim.set_state(s0)
    for k in range(12):
        sim._sim.step(1e-3, controls[k])
    for k in NAMES:
        assert np.array_equal(stored.outputs[k], getattr(sim, k)), f"rollout output {k} differs from plain steps"


def test_no_control_steps_equal_plain_steps_bitwise():
    sim = _scene(3, "neohookean", seed=1)
    s0 = sim.state()
    run = km.diff.rollout(sim, 3, 1e-3, wrt=("v",))
    sim.set_state(s0)
    for _ in range(3):
        sim.step(1e-3)
    assert all(np.array_equal(run.outputs[k], getattr(sim, k)) for k in NAMES)


@pytest.mark.parametrize("material", ["snow", "sand"])
def test_plastic_materials_are_refused_naming_material(material):
    sim = km.mpm.Simulation((16, 16), 1 / 16)
    sim.add_particles(km.mpm.block([0.3, 0.3], [0.5, 0.5], 1 / 32), "elastic", density=1000.0)
    kw = {"friction_angle": 30.0} if material == "sand" else {}
    sim.add_particles(km.mpm.block([0.6, 0.3], [0.7, 0.4], 1 / 32), material, density=1000.0, **kw)
    x0 = sim.x.copy()
    with pytest.raises(ValueError, match="material"):
        km.diff.rollout(sim, 2, 1e-3, wrt=("x",))
    assert np.array_equal(sim.x, x0), "a refused rollout must not step"


def test_bad_wrt_and_controls_raise_value_errors():
    sim = _scene(2, "elastic")
    with pytest.raises(ValueError, match="wrt"):
        km.diff.rollout(sim, 2, 1e-3, wrt=("mass",))
    with pytest.raises(ValueError, match="controls"):
        km.diff.rollout(sim, 2, 1e-3, wrt=("controls",))
    with pytest.raises(ValueError, match="controls"):
        km.diff.rollout(sim, 2, 1e-3, wrt=("x",), controls=np.zeros((2, sim.count, 3)))
    with pytest.raises(ValueError, match="cfl"):
        km.diff.rollout(sim, 2, 1e-3, wrt=("x",), cfl=0.5)
    assert sim.parameters == ("youngs_modulus", "poisson_ratio")


def test_actuation_example_runs_and_learns(tmp_path):
    """examples/diff_mpm_actuation.py with small settings: runs, writes its plots, and its
    gradient steps lower the loss (the walker ends further right)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "diff_mpm_actuation.py"
    spec = importlib.util.spec_from_file_location("diff_mpm_actuation", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    losses = module.main(["--out", str(tmp_path), "--iterations", "4", "--steps", "120", "--cells", "48"])
    assert (tmp_path / "loss.png").exists() and (tmp_path / "walker.png").exists()
    assert losses[-1] < losses[0], f"loss did not decrease over 4 iterations: {losses}"


def test_torch_bridge_gives_the_rollout_gradient():
    """km.torch over an MPM run: the gradient a torch loss gets for the per-particle Young's
    moduli equals km.diff's for the same loss."""
    torch = pytest.importorskip("torch")
    sim = _scene(2, "neohookean", seed=8)
    s0 = sim.state()
    E0 = sim.youngs_modulus.copy()
    E = torch.tensor(E0, dtype=torch.float64, requires_grad=True)
    out = km.torch.rollout(sim, 4, 1e-3, {"youngs_modulus": E})
    out["x"][:, 0].sum().backward()
    sim.set_state(s0)
    run = km.diff.rollout(sim, 4, 1e-3, wrt=("youngs_modulus",))
    g = run.backward({"x": np.column_stack([np.ones(sim.count), np.zeros(sim.count)])})["youngs_modulus"]
    assert np.array_equal(E.grad.numpy(), g), "km.torch's gradient differs from km.diff's"
    assert np.abs(g).max() > 0


@pytest.mark.parametrize("d", [2, 3])
def test_one_step_adjoint_is_bitwise_identical_for_1_and_2_threads(d):
    # Enough particles for the parallel transfers (above 1,024): G2P's transpose scatters into
    # per-block tiles that are summed per node in a fixed order, so the gradient is the same
    # bits whatever the thread count.
    sim = km.mpm.Simulation((32,) * d, 1 / 32, gravity=[0.0, -9.81, 0.0][:d], boundary="separate", friction=0.3)
    x = km.mpm.block([0.2] + [0.02] * (d - 1), [0.7] + [0.3] * (d - 1), 1 / 128 if d == 2 else 1 / 40)
    rng = np.random.default_rng(3)
    sim.add_particles(x, "elastic", density=1000.0, youngs_modulus=2e3, poisson_ratio=0.3,
                      velocity=rng.normal(0, 0.3, x.shape))
    assert sim.count > 1024, "enough particles for the parallel paths"
    results = step_adjoint_at_thread_counts(sim, 1e-3, None, 4, (1, 2))
    (g1, p1, _), (g2, p2, _) = results
    for k in g1:
        assert np.array_equal(g1[k], g2[k]), f"dL/d{k} differs between 1 and 2 threads"
    for k in p1:
        assert np.array_equal(np.asarray(p1[k]), np.asarray(p2[k])), f"dL/d{k} differs between 1 and 2 threads"
