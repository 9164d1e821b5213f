"""km.massspring's adjoint step (the km.diff protocol) against central finite differences, for
every integrator, parameter and control, in 2D and 3D; the dot-product test on an exactly
linear system; exact resume through state() / set_state()."""

import numpy as np
import pytest

import kinema as km

EPS = np.finfo(float).eps
INTEGRATORS = ("explicit", "symplectic", "implicit")


def lattice(dim, seed, *, scalar=False, compress=1.0, gravity=True):
    """A 4 x 4 cloth, randomly perturbed and moving, one corner fixed; per-item parameters
    (or scalars) drawn at random; springs at rest length * compress."""
    rng = np.random.default_rng(seed)
    x, springs = km.massspring.cloth(4, 4, 1.0, dim=dim)
    x = x + 0.05 * rng.standard_normal(x.shape)
    m = len(springs)
    rest = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1) * compress
    rest *= 1 + 0.1 * rng.standard_normal(m)
    if scalar:
        params = dict(stiffness=40.0, rest_length=rest, damping=0.2, mass=0.05)
    else:
        params = dict(stiffness=40.0 * (1 + 0.5 * rng.random(m)), rest_length=rest,
                      damping=0.2 * rng.random(m), mass=0.05 * (1 + rng.random(len(x))))
    g = (0.0, -9.81, 0.0)[:dim] if gravity else None
    s = km.massspring.System(x, springs, fixed=[0], gravity=g, **params)
    s.v[:] = 0.3 * rng.standard_normal(x.shape)
    s.v[0] = 0
    return s


def options(integrator):
    # The implicit step is differentiated as if solved exactly; the forward solve that the
    # finite differences see must then be exact too (a direct factorisation, rounding only).
    if integrator == "implicit":
        return dict(integrator="implicit", beta=0.8, linear_solver="cholmod_direct")
    return dict(integrator=integrator)


def fd_check(f, g_dot, h, what):
    """Central difference of the scalar function f(t) at 0 against g_dot = <grad, direction>.
    Truncation error of D(h) = (f(h) - f(-h)) / 2h is f'''(0) h^2 / 6 + O(h^4), estimated by
    Richardson from D(2h): |D(2h) - D(h)| / 3; rounding error at most 2 eps max|f| / (2h) per
    difference (f is evaluated to a few ulps), i.e. 4 eps max|f| / h on the estimate. The
    assertion allows twice their sum."""
    f0 = f(0.0)
    fp, fm, fp2, fm2 = f(h), f(-h), f(2 * h), f(-2 * h)
    d1 = (fp - fm) / (2 * h)
    d2 = (fp2 - fm2) / (4 * h)
    scale = max(abs(v) for v in (f0, fp, fm, fp2, fm2))
    bound = 2 * (abs(d2 - d1) / 3 + 4 * 16 * EPS * scale / h)
    err = abs(d1 - g_dot)
    assert err <= bound, (f"{what}: finite difference {d1:.12e}, adjoint {g_dot:.12e}, "
                          f"|diff| {err:.2e} > bound {bound:.2e} (h = {h})")
    return err, bound


def one_step_loss(sys, before, dt, opts, gx, gv):
    """L(t) for a perturbation: the loss <gx, x'> + <gv, v'> after one step."""
    def loss(state, params, control):
        sys.set_state(state)
        for k, v in params.items():
            sys._diff_set(k, v)
        sys._diff_step(dt, control, opts)
        return float(np.sum(gx * sys.x) + np.sum(gv * sys.v))
    return loss


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("scalar", [False, True])
def test_step_adjoint_matches_finite_differences(dim, integrator, scalar):
    sys = lattice(dim, seed=dim * 10 + INTEGRATORS.index(integrator), scalar=scalar)
    rng = np.random.default_rng(7)
    opts = options(integrator)
    dt = 0.01 if integrator != "implicit" else 0.05
    n, d = sys.x.shape
    control = rng.standard_normal((n, d))
    params0 = {k: sys._diff_get(k) for k in sys.parameters}
    before = sys.state()
    sys._diff_step(dt, control, opts)
    after = sys.state()
    gx, gv = rng.standard_normal((n, d)), rng.standard_normal((n, d))
    grad_before, grad_params, grad_control = sys._diff_step_adjoint(
        dt, before, after, control, {"x": gx, "v": gv}, opts)
    assert grad_control.shape == (n, d)
    for k in sys.parameters:
        # per item, even for a scalar parameter (km.diff sums the items last)
        count = n if k == "mass" else len(sys.springs)
        assert np.shape(grad_params[k]) == (count,), k
    loss = one_step_loss(sys, before, dt, opts, gx, gv)
    h = 1e-5
    for name in ("x", "v"):
        delta = rng.standard_normal((n, d))
        def f(t, name=name, delta=delta):
            s = dict(before)
            s[name] = before[name] + t * delta
            return loss(s, params0, control)
        fd_check(f, float(np.sum(grad_before[name] * delta)), h, f"{integrator} {dim}D d/d{name}")
    for k in sys.parameters:
        p0 = params0[k]
        delta = float(rng.standard_normal()) if np.ndim(p0) == 0 else rng.standard_normal(np.shape(p0))
        scale = np.abs(p0).max() if np.ndim(p0) else abs(p0)
        hp = h * scale
        def f(t, k=k, delta=delta, p0=p0):
            return loss(before, dict(params0, **{k: p0 + t * delta}), control)
        fd_check(f, float(np.sum(grad_params[k] * delta)), hp, f"{integrator} {dim}D d/d{k}")
    delta = rng.standard_normal((n, d))
    fd_check(lambda t: loss(before, params0, control + t * delta),
             float(np.sum(grad_control * delta)), h, f"{integrator} {dim}D d/dcontrol")
    # Fixed vertices ignore the control forces.
    assert np.all(grad_control[0] == 0)


@pytest.mark.parametrize("dim", [2, 3])
def test_clamped_implicit_step_is_differentiated_on_its_branch(dim):
    # Springs at 1.6 x their length and a long step: the exact Jacobian is indefinite and the
    # step clamps the transverse terms of the compressed springs; the gradient is that branch's.
    sys = lattice(dim, seed=3, compress=1.6, gravity=False)
    opts = dict(integrator="implicit", linear_solver="cholmod_direct")
    dt = 0.5
    rng = np.random.default_rng(1)
    n, d = sys.x.shape
    before = sys.state()
    info = sys.step(dt, **opts)
    assert info.clamped, "the set-up must take the clamped branch"
    after = sys.state()
    gx, gv = rng.standard_normal((n, d)), rng.standard_normal((n, d))
    grad_before, grad_params, _ = sys._diff_step_adjoint(dt, before, after, None, {"x": gx, "v": gv}, opts)
    params0 = {k: sys._diff_get(k) for k in sys.parameters}
    loss = one_step_loss(sys, before, dt, opts, gx, gv)
    delta = rng.standard_normal((n, d))
    def f(t):
        s = dict(before)
        s["x"] = before["x"] + t * delta
        value = loss(s, params0, None)
        assert sys.state()["clamped"], "the perturbation left the branch"
        return value
    fd_check(f, float(np.sum(grad_before["x"] * delta)), 1e-6, f"clamped {dim}D d/dx")
    k0 = params0["rest_length"]
    dk = rng.standard_normal(k0.shape)
    fd_check(lambda t: loss(before, dict(params0, rest_length=k0 + t * dk), None),
             float(np.sum(grad_params["rest_length"] * dk)), 1e-6, f"clamped {dim}D d/drest_length")


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_adjoint_is_the_transpose_of_the_linear_step(dim, integrator):
    # Zero rest lengths make the spring force -k d exactly linear (S = I, kernels.h), and
    # without gravity and damping the step is a linear map J of (x, v): J delta is the
    # difference of two steps exactly (to rounding, no truncation), and the adjoint must pass
    # the dot-product test <J delta, g> = <delta, J^T g>.
    rng = np.random.default_rng(dim)
    x, springs = km.massspring.cloth(4, 4, 1.0, dim=dim)
    sys = km.massspring.System(x, springs, stiffness=5.0 * (1 + rng.random(len(springs))),
                               rest_length=0.0, mass=0.1 * (1 + rng.random(len(x))), fixed=[0, 3])
    opts = options(integrator)
    dt = 0.02
    n, d = x.shape
    base = sys.state()
    dx, dv = rng.standard_normal((n, d)), rng.standard_normal((n, d))
    gx, gv = rng.standard_normal((n, d)), rng.standard_normal((n, d))

    def step(xx, vv):
        sys.set_state(dict(base, x=xx, v=vv))
        sys._diff_step(dt, None, opts)
        return sys.x.copy(), sys.v.copy()

    x1, v1 = step(base["x"] + dx, base["v"] + dv)
    x0, v0 = step(base["x"], base["v"])
    lhs = np.sum((x1 - x0) * gx) + np.sum((v1 - v0) * gv)
    grad, _, _ = sys._diff_step_adjoint(dt, dict(base), sys.state(), None, {"x": gx, "v": gv}, opts)
    rhs = np.sum(dx * grad["x"]) + np.sum(dv * grad["v"])
    scale = np.abs(x1).max() * np.abs(gx).sum() + np.abs(v1).max() * np.abs(gv).sum()
    assert abs(lhs - rhs) <= 1e3 * EPS * scale, (lhs, rhs, 1e3 * EPS * scale)


@pytest.mark.parametrize("integrator, linear_solver", [
    ("explicit", "cholmod"), ("symplectic", "cholmod"), ("implicit", "cholmod"),
    ("implicit", "cholmod_pcg"), ("implicit", "cholmod_direct"), ("implicit", "cg")])
def test_state_copy_resumes_bit_for_bit(integrator, linear_solver):
    # explicit and symplectic steps a quarter as long: below explicit_dt_limit (0.0149 s here)
    scale = 1.0 if integrator == "implicit" else 0.25

    def make():
        s = lattice(3, seed=5)
        s.step(0.01 * scale, integrator, linear_solver=linear_solver, steps=3)
        return s
    a = make()
    saved = a.state()
    a.step(0.02 * scale, integrator, linear_solver=linear_solver, steps=6)
    # A fresh system, and the same one after other steps: both resume from the copy exactly.
    for b in (make(), a):
        b.step(0.05 * scale, integrator, linear_solver=linear_solver, steps=2)
        b.set_state(saved)
        b.step(0.02 * scale, integrator, linear_solver=linear_solver, steps=6)
        np.testing.assert_array_equal(b.x, a.x if b is not a else ref_x)
        ref_x = b.x.copy()


def test_diff_protocol_errors():
    sys = lattice(2, seed=0)
    with pytest.raises(ValueError, match="steps"):
        sys._diff_check(("x",), {"steps": 2})
    with pytest.raises(ValueError, match="integrator"):
        sys._diff_check(("x",), {"integrator": "rk4"})
    with pytest.raises(ValueError, match="wrt"):
        sys._diff_check(("youngs_modulus",), {})
    with pytest.raises(ValueError, match="control"):
        sys._diff_step(0.01, np.zeros((3, 2)), {})
    with pytest.raises(ValueError, match="stiffness"):
        sys._diff_set("stiffness", -1.0)
    with pytest.raises(ValueError, match="state"):
        sys.set_state({"x": sys.x})
    assert sys._diff_control_shape() == sys.x.shape
    assert sys.parameters == ("stiffness", "rest_length", "mass", "damping")


# ---------------------------------------------------------------- km.diff rollouts

ROLLOUT_STEPS = 6


def run_loss(sys, start, params, controls, dt, opts, gx, gv):
    sys.set_state(start)
    for k, v in params.items():
        sys._diff_set(k, v)
    for c in controls:
        sys._diff_step(dt, c, opts)
    return float(np.sum(gx * sys.x) + np.sum(gv * sys.v))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_rollout_gradient_matches_finite_differences(dim, integrator):
    sys = lattice(dim, seed=40 + dim, scalar=(integrator == "symplectic"))
    rng = np.random.default_rng(11)
    opts = options(integrator)
    dt = 0.01 if integrator != "implicit" else 0.04
    n, d = sys.x.shape
    controls = 0.5 * rng.standard_normal((ROLLOUT_STEPS, n, d))
    start = sys.state()
    params0 = {k: sys._diff_get(k) for k in sys.parameters}
    wrt = ("x", "v", "controls") + sys.parameters
    run = km.diff.rollout(sys, ROLLOUT_STEPS, dt, wrt=wrt, controls=controls, **opts)
    gx, gv = rng.standard_normal((n, d)), rng.standard_normal((n, d))
    grads = run.backward({"x": gx, "v": gv})
    for name in wrt:
        value = start[name] if name in ("x", "v") else controls if name == "controls" else params0[name]
        delta = rng.standard_normal(np.shape(value)) if np.ndim(value) else float(rng.standard_normal())
        h = 1e-5 * (np.abs(value).max() if name in sys.parameters else 1.0)

        def f(t, name=name, delta=delta, value=value):
            s, p, c = dict(start), dict(params0), controls
            if name in ("x", "v"):
                s[name] = value + t * delta
            elif name == "controls":
                c = value + t * delta
            else:
                p[name] = value + t * delta
            return run_loss(sys, s, p, c, dt, opts, gx, gv)
        fd_check(f, float(np.sum(grads[name] * delta)), h, f"rollout {integrator} {dim}D d/d{name}")


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_checkpointed_chained_and_repeated_backward_agree(integrator):
    # The default implicit solver (PCG with the lagged factor) included: the recomputed steps
    # rebuild the factor from the State's record, so checkpointed = stored bit for bit.
    steps, dt = 20, 0.02 if integrator == "implicit" else 0.005
    opts = {"integrator": integrator}
    rng = np.random.default_rng(2)
    wrt = ("x", "v", "stiffness", "mass", "controls")

    def make():
        return lattice(3, seed=9)
    n, d = make().x.shape
    controls = rng.standard_normal((steps, n, d))
    g = {"x": rng.standard_normal((n, d)), "v": rng.standard_normal((n, d))}
    stored = km.diff.rollout(make(), steps, dt, wrt=wrt, controls=controls, **opts)
    a = stored.backward(g)
    K = int(2 * np.sqrt(steps))
    checked = km.diff.rollout(make(), steps, dt, wrt=wrt, controls=controls, checkpoints=K, **opts)
    np.testing.assert_array_equal(checked.outputs["x"], stored.outputs["x"])
    b = checked.backward(g)
    assert checked.peak_states <= K + 1, checked.peak_states
    for name in wrt:
        np.testing.assert_array_equal(a[name], b[name], err_msg=f"checkpointed {name}")
    again = stored.backward(g)
    for name in wrt:
        np.testing.assert_array_equal(a[name], again[name], err_msg=f"backward twice {name}")
    # Two rollouts of 12 + 8 steps chain to the one of 20.
    sys = make()
    first = km.diff.rollout(sys, 12, dt, wrt=wrt, controls=controls[:12], **opts)
    second = km.diff.rollout(sys, 8, dt, wrt=wrt, controls=controls[12:], **opts)
    np.testing.assert_array_equal(second.outputs["x"], stored.outputs["x"])
    g2 = second.backward(g)
    g1 = first.backward({"x": g2["x"], "v": g2["v"]})
    for name in ("x", "v"):
        np.testing.assert_allclose(g1[name], a[name], rtol=0, atol=1e-12 * np.abs(a[name]).max())
    for name in ("stiffness", "mass"):
        np.testing.assert_allclose(g1[name] + g2[name], a[name], rtol=0,
                                   atol=1e-12 * np.abs(a[name]).max())
    np.testing.assert_allclose(np.concatenate([g1["controls"], g2["controls"]]), a["controls"],
                               rtol=0, atol=1e-12 * np.abs(a["controls"]).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_gradient_of_momentum(dim, integrator):
    # Without fixed vertices and gravity the springs' forces cancel in pairs and every step
    # (the implicit one too: the spring blocks of A sum to zero over a spring's two rows) gives
    # P' = P + h sum_i u_i. For L = e . sum_i m_i v_i(T) with the weights m_i e held fixed:
    # dL/dv_i(0) = m_i e, dL/dx(0) = 0, dL/du_k = h e, dL/dk = 0, dL/dm_i = e . (v_i(0) - v_i(T)).
    rng = np.random.default_rng(dim)
    x, springs = km.massspring.cloth(4, 4, 1.0, dim=dim)
    x = x + 0.05 * rng.standard_normal(x.shape)
    mass = 0.1 * (1 + rng.random(len(x)))
    sys = km.massspring.System(x, springs, stiffness=30.0 * (1 + rng.random(len(springs))),
                               damping=0.1, mass=mass)
    sys.v[:] = rng.standard_normal(x.shape)
    v0 = sys.v.copy()
    steps, dt = 10, 0.01
    controls = rng.standard_normal((steps,) + x.shape)
    e = rng.standard_normal(dim)
    run = km.diff.rollout(sys, steps, dt, wrt=("x", "v", "controls", "stiffness", "mass", "damping"),
                          controls=controls, integrator=integrator,
                          **({"linear_solver": "cholmod_direct"} if integrator == "implicit" else {}))
    vT = run.outputs["v"]
    g = run.backward({"v": mass[:, None] * e})
    tol = 1e-12 * (np.abs(mass).max() * np.abs(e).max())
    np.testing.assert_allclose(g["v"], mass[:, None] * e[None, :], rtol=0, atol=1e3 * tol)
    np.testing.assert_allclose(g["x"], 0, atol=1e3 * tol)
    np.testing.assert_allclose(g["controls"], np.broadcast_to(dt * e, controls.shape), rtol=0, atol=1e3 * tol)
    np.testing.assert_allclose(g["mass"], (v0 - vT) @ e, rtol=0, atol=1e4 * tol * np.abs(vT).max())
    for name in ("stiffness", "damping"):
        np.testing.assert_allclose(g[name], 0, atol=1e4 * tol)


def test_lagged_adjoint_solve_agrees_with_direct():
    # The adjoint solve by PCG to adjoint_tol = 1e-12 against a fresh factorisation every step:
    # the relative residual r of each solve changes lambda by at most cond(A) r relative, and
    # A = M + h^2 K here has cond(A) <= 1 + h^2 |K| / m_min < 1e2 (Gershgorin: |K| <= 2 k per
    # spring end, 8 springs a vertex), so 20 steps stay below 20 * 1e2 * 1e-12 = 2e-9.
    steps, dt = 20, 0.02
    g = None
    out = {}
    for tol in (1e-12, 0.0):
        sys = lattice(3, seed=4)
        run = km.diff.rollout(sys, steps, dt, wrt=("x", "v", "stiffness"), adjoint_tol=tol)
        if g is None:
            rng = np.random.default_rng(0)
            g = {"x": rng.standard_normal(sys.x.shape), "v": rng.standard_normal(sys.x.shape)}
        out[tol] = run.backward(g)
    kmax = 40.0 * 1.5
    assert dt**2 * 16 * kmax / 0.05 < 1e2
    for name in ("x", "v", "stiffness"):
        err = np.abs(out[1e-12][name] - out[0.0][name]).max() / np.abs(out[0.0][name]).max()
        assert err < 2e-9, f"{name}: lagged vs direct adjoint differ by {err:.1e} (relative)"
    with pytest.raises(ValueError, match="adjoint_tol"):
        km.diff.rollout(lattice(2, seed=0), 1, dt, wrt=("x",), adjoint_tol=-1.0)


def _example(name):
    from pathlib import Path

    from load_script import load_script
    return load_script(Path(__file__).resolve().parent.parent / "examples" / f"{name}.py")


def test_walker_example_learns_to_move_right(tmp_path):
    walker = _example("diff_walker")
    losses = walker.main(["--out", str(tmp_path), "--iterations", "6", "--steps", "150"])
    assert (tmp_path / "walker_loss.png").stat().st_size > 0
    # loss = -x of the centre of mass after the run; it starts at x0.
    x0 = float(walker.robot()[0].x[:, 0].mean())
    assert losses[-1] < losses[0] - 0.02, losses  # trained, it walks at least 2 cm further
    assert -losses[-1] > x0 + 0.03, (x0, losses)  # and ends at least 3 cm right of its start


def test_walker_gradient_through_the_state_fed_controller_matches_finite_differences():
    """dL/d(W1, b1, W2, b2) of the walker (controller fed the state, ground forces fed back)
    along a random direction, and along the state inputs' weights alone, against central
    differences. h = 1e-5: the truncation error O(h^2) times the third derivative and the
    rounding error ~ 1e-16 |L| / h ~ 2e-12 are both far below 1e-6 of the derivative, as long as
    no vertex crosses the ground's kink within +-h (h = 1e-4 does cross one and disagrees)."""
    walker = _example("diff_walker")
    sys_, muscles = walker.robot()
    net = walker.initial_controller(muscles, len(sys_.x))
    rng = np.random.default_rng(1)
    full = [rng.standard_normal(p.shape) for p in net]
    state_only = [np.zeros_like(p) for p in net]
    state_only[0][:, walker.PHASES:] = full[0][:, walker.PHASES:]
    steps, dt, h = 30, 1.5e-3, 1e-5
    _, _, grads = walker.simulate(net, steps, dt, grad=True)
    for direction in (full, state_only):
        ad = sum(np.sum(g * d) for g, d in zip(grads, direction))
        plus = walker.simulate([p + h * d for p, d in zip(net, direction)], steps, dt)[0]
        minus = walker.simulate([p - h * d for p, d in zip(net, direction)], steps, dt)[0]
        fd = (plus - minus) / (2 * h)
        assert abs(ad - fd) <= 1e-6 * abs(fd), (ad, fd)


def test_cloth_throw_example_reaches_the_target(tmp_path):
    losses = _example("diff_cloth_throw").main(
        ["--out", str(tmp_path), "--iterations", "6", "--n", "6", "--steps", "20"])
    assert (tmp_path / "cloth_throw_loss.png").stat().st_size > 0
    # Gradient descent on a nearly linear map: the miss shrinks by orders of magnitude.
    assert losses[-1] < 1e-3 * losses[0], losses


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_run_stored_in_cpp_equals_the_step_by_step_path_bitwise(integrator, monkeypatch):
    # A stored run goes through System._diff_record (steps and adjoints in C++); without that
    # hook km.diff takes the steps one by one through the protocol. Same bits either way.
    steps, dt = 12, 0.02 if integrator == "implicit" else 0.005
    rng = np.random.default_rng(5)
    wrt = ("x", "v", "stiffness", "rest_length", "damping", "mass", "controls")
    n, d = lattice(3, seed=4).x.shape
    controls = rng.standard_normal((steps, n, d))
    g = {"x": rng.standard_normal((n, d)), "v": rng.standard_normal((n, d))}
    fast = km.diff.rollout(lattice(3, seed=4), steps, dt, wrt=wrt, controls=controls, integrator=integrator)
    assert fast._record is not None
    a = fast.backward(g)
    monkeypatch.setattr(km.massspring.System, "_diff_record", lambda *args: None)
    slow = km.diff.rollout(lattice(3, seed=4), steps, dt, wrt=wrt, controls=controls, integrator=integrator)
    assert slow._record is None
    b = slow.backward(g)
    for name in ("x", "v"):
        np.testing.assert_array_equal(fast.outputs[name], slow.outputs[name])
    for name in wrt:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    # Only the state gradient asked for: the same bits, no parameter gradients computed.
    only_v = km.diff.rollout(lattice(3, seed=4), steps, dt, wrt=("v",), controls=controls, integrator=integrator)
    np.testing.assert_array_equal(only_v.backward(g)["v"], a["v"])


def test_avx2_spring_passes_give_the_baseline_bits(monkeypatch):
    """The 2D explicit step's and its adjoint's AVX2 spring passes perform the scalar loop's
    operations in its order (no FMA): a rollout and its gradients are bitwise those of the
    baseline build (KINEMA_SIMD=baseline, read when a System is made). 61 springs: the four-wide
    loop's tail runs too; one spring of zero length (masked lanes)."""
    x, springs = km.massspring.cloth(4, 5, (0.3, 0.4), dim=2)
    x = np.vstack([x, x[:1]])  # a duplicate of vertex 0, tied to it by a zero-length spring
    springs = np.vstack([springs, [[0, len(x) - 1]]])
    assert len(springs) % 4 != 0
    rng = np.random.default_rng(3)
    rest = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1) * (1 + 0.1 * rng.random(len(springs)))
    stiffness = 50.0 * (1 + rng.random(len(springs)))
    out = {}
    for simd in ("baseline", "default"):
        if simd == "baseline":
            monkeypatch.setenv("KINEMA_SIMD", "baseline")
        else:
            monkeypatch.delenv("KINEMA_SIMD", raising=False)
        sim = km.massspring.System(x, springs, stiffness=stiffness,
                                   rest_length=rest, damping=0.3, mass=0.05, gravity=(0.0, -9.81), fixed=[1])
        sim.v = 0.1 * np.random.default_rng(4).standard_normal(x.shape)
        run = km.diff.rollout(sim, 20, 1e-3, wrt=("x", "v", "stiffness", "rest_length", "damping", "mass"),
                              integrator="symplectic")
        out[simd] = run.outputs, run.backward({"x": np.ones_like(x), "v": np.full_like(x, 0.5)})
    for part in (0, 1):
        for name, value in out["baseline"][part].items():
            assert np.isfinite(value).all(), name
            np.testing.assert_array_equal(out["default"][part][name], value, err_msg=name)


def big_cloth(dim, seed, *, scramble):
    """A 48 x 48 cloth with structural, shear and bending springs (13,346: more than the 2048
    below which the explicit passes run on one thread), perturbed and moving, per-item
    parameters, two corners fixed. Numbered row by row, a spring reaches about 100 vertices, so
    the passes keep a ring of slots far shorter than the slot list (spring_pass.h); scramble:
    the vertices renumbered at random, so that the ring is the whole list."""
    rng = np.random.default_rng(seed)
    x, springs = km.massspring.cloth(48, 48, 1.0, dim=dim)
    fixed = [0, 47]
    if scramble:
        perm = rng.permutation(len(x))  # new index of each vertex
        inverse = np.empty_like(perm)
        inverse[perm] = np.arange(len(x))
        x, springs, fixed = x[inverse], perm[springs], perm[fixed]
    x = x + 0.002 * rng.standard_normal(x.shape)
    m = len(springs)
    rest = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1) * (1 + 0.05 * rng.standard_normal(m))
    s = km.massspring.System(x, springs, stiffness=40.0 * (1 + 0.5 * rng.random(m)), rest_length=rest,
                             damping=0.02 * rng.random(m), mass=1e-3 * (1 + rng.random(len(x))),
                             fixed=fixed, gravity=(0.0, -9.81, 0.0)[:dim])
    s.v[:] = 0.05 * rng.standard_normal(x.shape)
    s.v[fixed] = 0
    return s, np.asarray(fixed)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("scramble", [False, True])
def test_threaded_explicit_passes_are_the_assembled_forces_at_any_thread_count(dim, scramble):
    """The explicit passes (pass order, per-thread rings, springs evaluated on both sides of a
    thread boundary) sum each vertex's spring forces in the model's spring order, as the
    assembled f(x, v) does: a symplectic step is v' = v + h f / m and x' = x + h v' bit for bit,
    and a rollout and its gradients are bitwise the same for 1, 2 and 3 threads."""
    dt, steps = 2e-4, 6
    wrt = ("x", "v", "stiffness", "rest_length", "damping", "mass")
    before = km.get_num_threads()
    out = {}
    try:
        for threads in (1, 2, 3):
            km.set_num_threads(threads)
            sys, fixed = big_cloth(dim, seed=dim, scramble=scramble)
            x0, v0, f = sys.x.copy(), sys.v.copy(), sys.forces()
            sys.step(dt, "symplectic")
            free = np.ones(len(x0), bool)
            free[fixed] = False
            expected_v = v0 + dt * f / sys._diff_get("mass")[:, None]
            np.testing.assert_array_equal(sys.v[free], expected_v[free])
            assert np.all(sys.v[fixed] == 0)
            np.testing.assert_array_equal(sys.x[free], (x0 + dt * sys.v)[free])
            np.testing.assert_array_equal(sys.x[fixed], x0[fixed])
            sys, _ = big_cloth(dim, seed=dim, scramble=scramble)
            run = km.diff.rollout(sys, steps, dt, wrt=wrt, integrator="symplectic")
            rng = np.random.default_rng(1)
            grads = run.backward({"x": rng.standard_normal(x0.shape), "v": rng.standard_normal(x0.shape)})
            out[threads] = run.outputs, grads
    finally:
        km.set_num_threads(before)
    for threads in (2, 3):
        for part in (0, 1):
            for name, value in out[1][part].items():
                assert np.isfinite(value).all(), name
                np.testing.assert_array_equal(out[threads][part][name], value,
                                              err_msg=f"{name}, {threads} threads")


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_threaded_explicit_gradients_match_finite_differences(dim, integrator):
    """A rollout through the threaded passes of a large, randomly numbered cloth (two threads:
    each evaluates the springs reaching into its range from the other's) against central
    differences of the forward run, for the state and every parameter."""
    dt, steps = 2e-4, 8
    wrt = ("x", "v", "stiffness", "rest_length", "damping", "mass")
    before = km.get_num_threads()
    try:
        km.set_num_threads(2)
        sys, fixed = big_cloth(dim, seed=10 + dim, scramble=True)
        start = sys.state()
        params0 = {k: sys._diff_get(k) for k in wrt[2:]}
        rng = np.random.default_rng(3)
        w = rng.standard_normal(sys.x.shape)
        run = km.diff.rollout(sys, steps, dt, wrt=wrt, integrator=integrator)
        grads = run.backward({"x": w})

        def loss(state, params):
            sys.set_state(state)
            for k, p in params.items():
                sys._diff_set(k, p)
            sys.step(dt, integrator, steps=steps)
            value = float(np.sum(w * sys.x))
            for k, p in params0.items():
                sys._diff_set(k, p)
            return value
        for name in ("x", "v"):
            delta = rng.standard_normal(sys.x.shape)
            delta[fixed] = 0
            def f(t, name=name, delta=delta):
                return loss(dict(start, **{name: start[name] + t * delta}), {})
            fd_check(f, float(np.sum(grads[name] * delta)), 1e-6, f"{integrator} {dim}D d/d{name}")
        for k, p0 in params0.items():
            delta = rng.standard_normal(np.shape(p0))
            fd_check(lambda t, k=k, p0=p0, delta=delta: loss(start, {k: p0 + t * delta}),
                     float(np.sum(grads[k] * delta)), 1e-6 * np.abs(p0).max(), f"{integrator} {dim}D d/d{k}")
    finally:
        km.set_num_threads(before)


def test_diverging_stored_run_stops_where_plain_steps_stop():
    """A stored explicit run steps straight into the states it keeps; a step that diverges
    raises DivergenceError naming v and leaves the system at the state before that step, as the
    same steps taken one by one do."""
    a, _ = big_cloth(2, seed=1, scramble=False)
    b, _ = big_cloth(2, seed=1, scramble=False)
    # Just below unstable_dt (above it the step is refused before running): warned, and unstable.
    dt = 0.99 * a.unstable_dt
    with pytest.warns(RuntimeWarning, match="explicit_dt_limit"), \
            pytest.raises(km.DivergenceError, match="v: non-finite"):
        for _ in range(2000):
            a.step(dt, "symplectic")
    with pytest.warns(RuntimeWarning, match="explicit_dt_limit"), \
            pytest.raises(km.DivergenceError, match="v: non-finite"):
        km.diff.rollout(b, 2000, dt, wrt=("v",), integrator="symplectic")
    assert a.state()["step"] == b.state()["step"] > 0
    assert np.isfinite(b.x).all() and np.isfinite(b.v).all()
    np.testing.assert_array_equal(b.x, a.x)
    np.testing.assert_array_equal(b.v, a.v)
