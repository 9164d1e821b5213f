"""Gradients through km.fem.Body: the C++ adjoint step against central finite differences of the
forward step for every integrator x model x parameter in 2D and 3D, whole rollouts through
km.diff (stored and checkpointed, chained, controls), the gradient of a conserved quantity, exact
state resume, and the errors.

Finite-difference error bound. For D(h) = (L(p + h e) - L(p - h e)) / 2h the truncation error is
h^2 |L'''| / 6 + O(h^4); D(h) - D(2h) = -3 h^2 |L'''| / 6 + ..., so |D(h) - D(2h)| estimates
three times the truncation error of D(h) and is used as its bound. Rounding adds
eps_L / h, eps_L the noise of one evaluation of L: the Newton solution stops at a gradient
~1e-13 of its terms (cholmod_direct, tol 1e-12), so eps_L <= 1e-11 sum |w . y| over the
outputs y; the bound takes 1e-10 to cover the sums that form L.
"""

import numpy as np
import pytest

import kinema as km
from kinema import diff

MODELS = km.fem.MODELS
EXACT = dict(tol=1e-12, linear_solver="cholmod_direct")


def body(d, model="neohookean", *, seed=0, per_element=True, damping=0.3, fixed=True, gravity=True,
         cells=None):
    rng = np.random.default_rng(seed)
    if d == 2:
        V, T = km.fem.rectangle_mesh([0, 0], [1, 0.4], cells or (4, 2))
    else:
        V, T = km.fem.box_mesh([0, 0, 0], [1, 0.4, 0.4], cells or (3, 1, 1))
    m = len(T)
    E = 1e4 * (1 + 0.3 * rng.random(m)) if per_element else 1.2e4
    nu = 0.3 + 0.05 * rng.random(m) if per_element else 0.32
    g = (0, -9.81, 0)[:d] if gravity else None
    b = km.fem.Body(V, T, model=model, youngs_modulus=E, poisson_ratio=nu, density=50.0,
                    fixed=np.flatnonzero(V[:, 0] < 1e-9) if fixed else (), gravity=g,
                    damping=damping)
    # A deformed, moving start so that every term of the step is exercised.
    b.v = 0.3 * rng.standard_normal(b.v.shape)
    b.x = b.x + 0.02 * rng.standard_normal(b.x.shape)
    return b


def central(f, h):
    """(D(h), bound on its error) for the scalar function f(t) at t = 0 (module docstring)."""
    f1, f_1, f2, f_2 = f(h), f(-h), f(2 * h), f(-2 * h)
    d1 = (f1 - f_1) / (2 * h)
    d2 = (f2 - f_2) / (4 * h)
    scale = max(abs(f1), abs(f_1), abs(f2), abs(f_2))
    return d1, abs(d1 - d2) + 1e-10 * scale / h


def check(what, adjoint, fd, bound):
    err = abs(adjoint - fd)
    assert err <= bound + 1e-12 * abs(fd), (
        f"{what}: adjoint {adjoint:.12e}, central difference {fd:.12e}, |difference| {err:.3e} "
        f"> bound {bound:.3e}")


def step_gradients(b, dt, options, rng):
    """One step's adjoint against central differences along random directions of every input."""
    shape = b.x.shape
    u = 0.5 * rng.standard_normal(shape)
    w_x, w_v = rng.standard_normal(shape), rng.standard_normal(shape)
    s0 = b.state()

    def loss():
        return float((w_x * b.x).sum() + (w_v * b.v).sum())

    b._diff_step(dt, u, options)
    grads, gp, gu = b._diff_step_adjoint(dt, s0, b.state(), u, {"x": w_x, "v": w_v}, options)
    assert gu.shape == shape and grads["x"].shape == shape and grads["v"].shape == shape

    for name in ("x", "v"):
        e = rng.standard_normal(shape)

        def f(t, name=name, e=e):
            s = dict(s0)
            s[name] = s0[name] + t * e
            b.set_state(s)
            b._diff_step(dt, u, options)
            return loss()

        fd, bound = central(f, 1e-6)
        check(f"d/d{name}", float((grads[name] * e).sum()), fd, bound)

    e = rng.standard_normal(shape)

    def f_u(t):
        b.set_state(s0)
        b._diff_step(dt, u + t * e, options)
        return loss()

    fd, bound = central(f_u, 1e-3)
    check("d/dcontrol", float((gu * e).sum()), fd, bound)

    for name in b.parameters:
        p0 = b._diff_get(name)
        e = rng.standard_normal(np.shape(p0)) if np.ndim(p0) else 1.0
        h = {"youngs_modulus": 1e-3 * np.max(p0), "poisson_ratio": 1e-4, "density": 1e-3 * p0,
             "damping": 1e-4}[name]

        def f_p(t, name=name, p0=p0, e=e):
            b._diff_set(name, p0 + t * e)
            b.set_state(s0)
            b._diff_step(dt, u, options)
            b._diff_set(name, p0)
            return loss()

        fd, bound = central(f_p, h)
        g = gp[name]
        assert np.shape(g) == np.shape(p0), f"d/d{name}: shape {np.shape(g)} != {np.shape(p0)}"
        check(f"d/d{name}", float(np.sum(g * e)), fd, bound)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_step_adjoint_matches_central_differences(d, model, integrator):
    b = body(d, model, seed=10 * d + MODELS.index(model) + 100 * (integrator == "implicit"))
    dt = 0.01 if integrator == "implicit" else 2e-4
    assert dt < b.explicit_dt_limit or integrator == "implicit"
    step_gradients(b, dt, dict(EXACT, integrator=integrator), np.random.default_rng(d))


@pytest.mark.parametrize("d", [2, 3])
def test_step_adjoint_uniform_parameters_and_lagged_solver(d):
    """Scalar parameters give float gradients; the default lagged-CHOLMOD Newton converges to
    the same minimiser, so its adjoint (always an exact solve) agrees as well."""
    b = body(d, "corotated", per_element=False)
    assert isinstance(b._diff_get("youngs_modulus"), float)
    step_gradients(b, 0.02, dict(tol=1e-12), np.random.default_rng(5))


@pytest.mark.slow
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("model", MODELS)
def test_step_adjoint_larger_mesh_large_steps(d, model):
    b = body(d, model, cells=(10, 4) if d == 2 else (6, 2, 2), damping=0.05, seed=3)
    step_gradients(b, 0.05, EXACT, np.random.default_rng(9))


def rollout_fd(make, steps, dt, wrt, controls, options, rng, checkpoints=None):
    """Rollout gradients of L = w_x . x_T + w_v . v_T against central differences."""
    sim = make()
    run = diff.rollout(sim, steps, dt, wrt=wrt, controls=controls, checkpoints=checkpoints, **options)
    w_x, w_v = rng.standard_normal(sim.x.shape), rng.standard_normal(sim.x.shape)
    grads = run.backward({"x": w_x, "v": w_v})
    for name in wrt:
        s = make()
        p0 = controls if name == "controls" else s._diff_get(name)
        e = rng.standard_normal(np.shape(p0)) if np.ndim(p0) else 1.0
        h = {"x": 1e-6, "v": 1e-6, "controls": 1e-3, "youngs_modulus": 10.0, "poisson_ratio": 1e-4,
             "density": 0.05, "damping": 1e-4}[name]

        def f(t, name=name, p0=p0, e=e):
            s = make()
            u = controls
            if name == "controls":
                u = p0 + t * e
            else:
                s._diff_set(name, p0 + t * e)
            for k in range(steps):
                s._diff_step(dt, None if u is None else u[k], options)
            return float((w_x * s.x).sum() + (w_v * s.v).sum())

        fd, bound = central(f, h)
        check(f"rollout d/d{name}", float(np.sum(grads[name] * e)), fd, bound)
    return run, grads, (w_x, w_v)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_rollout_matches_central_differences(d, integrator):
    rng = np.random.default_rng(11)
    steps = 6 if integrator == "implicit" else 20
    dt = 0.01 if integrator == "implicit" else 2e-4
    make = lambda: body(d, "neohookean", seed=4)  # noqa: E731
    u = 0.3 * rng.standard_normal((steps,) + make().x.shape)
    wrt = ("x", "v", "controls") + km.fem.Body.parameters
    rollout_fd(make, steps, dt, wrt, u, dict(EXACT, integrator=integrator), rng)


def test_checkpointed_equals_stored_and_backward_twice():
    """K = 2 sqrt(T) checkpoints give the stored run's gradients (the recomputed steps are
    bitwise the same: the lagged factor is in the State), and backward is repeatable."""
    steps, dt = 16, 0.02
    make = lambda: body(3, "stvk", seed=6)  # noqa: E731
    rng = np.random.default_rng(2)
    u = 0.2 * rng.standard_normal((steps,) + make().x.shape)
    wrt = ("x", "v", "controls", "youngs_modulus", "density")
    w = {"x": rng.standard_normal(make().x.shape), "v": rng.standard_normal(make().x.shape)}
    stored = diff.rollout(make(), steps, dt, wrt=wrt, controls=u)  # default lagged CHOLMOD
    checked = diff.rollout(make(), steps, dt, wrt=wrt, controls=u, checkpoints=8)
    assert np.array_equal(stored.outputs["x"], checked.outputs["x"])
    a, b, again = stored.backward(w), checked.backward(w), stored.backward(w)
    for name in wrt:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        np.testing.assert_array_equal(a[name], again[name], err_msg=name)


def test_chained_rollouts_equal_one_rollout():
    steps, dt = 8, 0.02
    make = lambda: body(2, "corotated", seed=8)  # noqa: E731
    rng = np.random.default_rng(3)
    w = {"x": rng.standard_normal(make().x.shape), "v": rng.standard_normal(make().x.shape)}
    wrt = ("x", "v", "youngs_modulus", "damping")
    one = diff.rollout(make(), steps, dt, wrt=wrt).backward(w)
    sim = make()
    first = diff.rollout(sim, steps // 2, dt, wrt=wrt)
    second = diff.rollout(sim, steps - steps // 2, dt, wrt=wrt)
    g2 = second.backward(w)
    g1 = first.backward({"x": g2["x"], "v": g2["v"]})
    scale = {k: np.max(np.abs(one[k])) for k in wrt}
    for k in ("x", "v"):
        np.testing.assert_allclose(g1[k], one[k], rtol=0, atol=1e-12 * scale[k], err_msg=k)
    for k in ("youngs_modulus", "damping"):
        np.testing.assert_allclose(np.asarray(g1[k]) + np.asarray(g2[k]), one[k], rtol=0,
                                   atol=1e-12 * scale[k], err_msg=k)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_gradient_of_conserved_momentum(d, integrator):
    """Without gravity, damping, controls or fixed vertices, elastic forces cancel in sum, so
    P = sum m_i v_i is conserved by both steps: for L = e . P_T, dL/dv_0 = m_i e, dL/dx_0 = 0,
    and dL/dE = dL/dnu = dL/drho = 0 (with the weights m_i fixed in L, sum (m_i/rho) v_i is
    conserved whatever rho)."""
    b = body(d, "neohookean", damping=0.0, fixed=False, gravity=False)
    e = np.random.default_rng(1).standard_normal(d)
    P0 = b.mass @ b.v
    dt = 0.01 if integrator == "implicit" else 2e-4
    run = diff.rollout(b, 5, dt, wrt=("x", "v") + b.parameters, integrator=integrator, **EXACT)
    np.testing.assert_allclose(b.mass @ b.v, P0, rtol=1e-10, atol=1e-12)
    g = run.backward({"v": b.mass[:, None] * e})
    scale = np.abs(b.mass).max() * np.abs(e).max()
    np.testing.assert_allclose(g["v"], b.mass[:, None] * e, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(g["x"], 0, atol=1e-9 * scale / dt)
    assert abs(g["density"]) <= 1e-9 * np.abs(P0).sum() / 50.0
    E = b._diff_get("youngs_modulus")
    assert np.abs(g["youngs_modulus"]).max() <= 1e-9 * np.abs(P0).sum() / E.min()


def test_set_state_resumes_bitwise_with_a_fresh_body():
    """The lagged CHOLMOD factor is part of the state: a new body restored from state() steps
    bitwise as the original does."""
    a = body(3, "neohookean", seed=2)
    for _ in range(3):
        a.step(0.02)
    saved = a.state()
    b = body(3, "neohookean", seed=2)
    b.set_state(saved)
    for _ in range(3):
        sa, sb = a.step(0.02), b.step(0.02)
        assert sa.cg_iterations == sb.cg_iterations
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)
    assert a.state()["steps"] == 6 and a.time == b.time


def test_errors_name_the_argument():
    b = body(2)
    with pytest.raises(ValueError, match="wrt"):
        diff.rollout(b, 2, 0.01, wrt=("stiffness",))
    with pytest.raises(ValueError, match="beta"):
        diff.rollout(b, 2, 0.01, wrt=("x",), beta=0.5)
    with pytest.raises(ValueError, match="steps"):
        b._diff_check(("x",), {"steps": 3})
    with pytest.raises(ValueError, match="integrator"):
        diff.rollout(b, 2, 0.01, wrt=("x",), integrator="explicit")
    with pytest.raises(ValueError, match="controls"):
        diff.rollout(b, 2, 0.01, wrt=("x",), controls=np.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="youngs_modulus"):
        b._diff_set("youngs_modulus", np.ones(3))
    with pytest.raises(ValueError, match="poisson_ratio"):
        b._diff_set("poisson_ratio", 0.5)
    assert b._diff_get("poisson_ratio").shape == (len(b.elements),)  # the refused value left no trace
    with pytest.raises(ValueError, match="dt"):
        b.step(-1.0)


def test_fixed_vertices_ignore_controls_and_get_no_velocity_gradient():
    b = body(3, "linear", seed=1)
    fixed = b.fixed
    rng = np.random.default_rng(0)
    u = rng.standard_normal((3,) + b.x.shape)
    x0 = b.x[fixed].copy()
    run = diff.rollout(b, 3, 0.01, wrt=("v", "controls"), controls=u, **EXACT)
    assert np.array_equal(b.x[fixed], x0)
    g = run.backward({"x": rng.standard_normal(b.x.shape)})
    assert not g["controls"][:, fixed].any() and not g["v"][fixed].any()


def test_beam_identification_example_smoke(tmp_path):
    from pathlib import Path

    from load_script import load_script

    example = load_script(Path(__file__).resolve().parents[1] / "examples" / "diff_beam_identify.py")
    losses, error = example.main(["--out", str(tmp_path), "--cells", "8", "2", "--steps", "6",
                                  "--iterations", "6"])
    assert losses[-1] < 0.5 * losses[0], losses
    assert (tmp_path / "loss.png").stat().st_size > 0 and (tmp_path / "modulus.png").exists()


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_parameter_mask_leaves_state_gradients_unchanged(d, integrator):
    """backward computes only the parameter gradients in wrt (km.diff's _diff_want mask): the
    state and control gradients are bitwise those of a run that asks for every parameter, each
    parameter asked alone gets the all-parameter run's value bitwise, checkpointed runs agree with
    stored ones, and the mask is lifted after backward (a direct adjoint step returns them all)."""
    steps = 4 if integrator == "implicit" else 12
    dt = 0.01 if integrator == "implicit" else 2e-4
    options = dict(EXACT, integrator=integrator)
    make = lambda: body(d, "neohookean", seed=8)  # noqa: E731
    rng = np.random.default_rng(5)
    u = 0.3 * rng.standard_normal((steps,) + make().x.shape)
    w = {"x": rng.standard_normal(make().x.shape), "v": rng.standard_normal(make().x.shape)}
    states = ("x", "v", "controls")
    full = diff.rollout(make(), steps, dt, wrt=states + km.fem.Body.parameters, controls=u,
                        **options).backward(w)
    sim = make()
    masked = diff.rollout(sim, steps, dt, wrt=states, controls=u, **options).backward(w)
    checked = diff.rollout(make(), steps, dt, wrt=states, controls=u, checkpoints=3,
                           **options).backward(w)
    for name in states:
        assert np.any(full[name] != 0), name
        np.testing.assert_array_equal(masked[name], full[name], err_msg=name)
        np.testing.assert_array_equal(checked[name], full[name], err_msg=name)
    for name in km.fem.Body.parameters:
        alone = diff.rollout(make(), steps, dt, wrt=("v", name), controls=u, **options).backward(w)
        assert np.any(np.asarray(full[name]) != 0), name
        np.testing.assert_array_equal(alone[name], full[name], err_msg=name)
        np.testing.assert_array_equal(alone["v"], full["v"], err_msg=name)
    # After the masked backward, a direct adjoint step gives every parameter again.
    s0 = sim.state()
    sim._diff_step(dt, u[0], options)
    _, gp, _ = sim._diff_step_adjoint(dt, s0, sim.state(), u[0], w, options)
    assert set(gp) == set(km.fem.Body.parameters)


def _per_step(sim):
    """sim with km.diff's stored C++ run switched off (the step-by-step path)."""
    sim._diff_record = lambda *args: None
    return sim


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
@pytest.mark.parametrize("per_element", [True, False])
def test_stored_cpp_run_equals_the_step_by_step_path_bitwise(d, integrator, per_element):
    """The stored run (Body._diff_record: forward and reverse in C++) gives the step-by-step
    path's gradients bit for bit: each adjoint step is the same C++ function on the same states
    (and the same lagged-factor records), and the parameter gradients are summed in the same
    order (a uniform parameter's per step in C++ on both paths, then over the steps)."""
    steps = 5 if integrator == "implicit" else 15
    dt = 0.01 if integrator == "implicit" else 2e-4
    make = lambda: body(d, "neohookean", seed=12, per_element=per_element)  # noqa: E731
    rng = np.random.default_rng(7)
    u = 0.3 * rng.standard_normal((steps,) + make().x.shape)
    w = {"x": rng.standard_normal(make().x.shape), "v": rng.standard_normal(make().x.shape)}
    wrt = ("x", "v", "controls") + km.fem.Body.parameters
    stored = diff.rollout(make(), steps, dt, wrt=wrt, controls=u, integrator=integrator)
    assert stored._record is not None  # the C++ run was taken
    stepwise = diff.rollout(_per_step(make()), steps, dt, wrt=wrt, controls=u, integrator=integrator)
    assert stepwise._record is None
    for name in ("x", "v"):
        np.testing.assert_array_equal(stored.outputs[name], stepwise.outputs[name], err_msg=name)
    a, b = stored.backward(w), stepwise.backward(w)
    for name in wrt:
        assert np.all(np.isfinite(a[name])) and np.any(np.asarray(a[name]) != 0), name
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    for name in ("youngs_modulus", "poisson_ratio"):
        assert np.ndim(a[name]) == (1 if per_element else 0), name


@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_stored_cpp_run_matches_central_differences_and_restores_on_failure(integrator):
    """The stored run's gradient (3D neo-Hookean: the lane passes of the element terms) against
    a central difference of the forward run, and a record whose step diverges leaves the body
    at the last completed step, as step-by-step calls do."""
    rng = np.random.default_rng(21)
    steps = 4 if integrator == "implicit" else 20
    dt = 0.01 if integrator == "implicit" else 2e-4
    make = lambda: body(3, "neohookean", seed=5, cells=(4, 2, 2))  # noqa: E731
    u = 0.3 * rng.standard_normal((steps,) + make().x.shape)
    rollout_fd(make, steps, dt, ("v", "youngs_modulus"), u, dict(EXACT, integrator=integrator), rng)
    ends = []
    for b in (make(), _per_step(make())):
        with pytest.raises(km.DivergenceError):
            diff.rollout(b, 5, 2e-4, wrt=("v",), integrator="symplectic",
                         controls=np.full((5,) + b.x.shape, 1e300))
        ends.append(b.state())
    assert 0 < ends[0]["steps"] < 5 and ends[0]["steps"] == ends[1]["steps"]
    for name in ("x", "v"):
        assert np.all(np.isfinite(ends[0][name])), name
        np.testing.assert_array_equal(ends[0][name], ends[1][name], err_msg=name)
