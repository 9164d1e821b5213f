"""Gradients of km.sph's WCSPH (Solver::step_adjoint and km.diff rollouts) against central finite
differences, in 2D and 3D, for every differentiable input (x, v), the per-step particle forces
(controls) and the viscosity: a compressed fluid in a closed box (Akinci boundary samples), a
free droplet reordered along the Morton curve every step (rows permuted during the run), and
particles clamped back into the domain.

Two references. kinema's forward stores its kernel gradients in single precision
(solver.cpp, kernel_rows), each component rounded by a relative 2^-24, so the acceleration of
particle i is off by at most 2^-24 A_i, A_i = sum_j (m |P_i + P_j| + |c_ij|) |grad W_ij| the sum
of the magnitudes of its pressure and viscosity terms; the adjoint is the exact derivative of
the step in double precision. So (1) a NumPy transcription of the step in double precision is
checked against the forward within that bound (test_reference_step_matches_the_forward), and
the adjoint is checked (2) tightly against central differences of the reference, and (3) for
one step against differences of the forward as run, with the single-precision bound.

Tolerance of a check along a random direction r with step e: D(e) = (L(p + e r) - L(p - e r)) / 2e
of L = <W, state> differs from the derivative by a truncation c e^2 + O(e^4) and by at most
delta / e, where delta bounds the rounding of one evaluation of L: 1e3 u sum |W| |state| in
double precision (u = 2^-53; every entry is a sum of at most ~100 terms per step), plus, for
the forward as run, delta_float = sum_t sum_i |lambda_i^t| 2^-24 A_i^t to first order, with
lambda^t = dL/da^t = m dL/d(controls_t), which the adjoint itself gives. The truncation is
measured: D(e) - D(2e) = -3 c e^2 + O(e^4). A check passes when
|adjoint - D(e)| <= |D(2e) - D(e)| + 2 delta / e, and must be informative: the bound below
1e-3 |D| against the reference, 5e-2 |D| against the forward as run (single-precision
differences resolve no better). Tait's equation of state clamps p = 0 at rho <= rho0 (a kink):
every check first asserts that no particle's density crossed rho0 between the evaluations
(a difference across it would not measure the derivative).
"""

import numpy as np
import pytest

import kinema as km

U = np.finfo(float).eps / 2
UF = 2.0 ** -24
NAMES = ("x", "v")
STEPS = {"x": 1e-5, "v": 1e-3, "controls": 1.0, "viscosity": 1e-3}
STEPS_REFERENCE = {"x": 1e-7, "v": 1e-6, "controls": 1e-2, "viscosity": 1e-6}
DT = 2e-4
SPACING = 0.02


def _scene(d, kind, seed=0, packing=0.95):
    """kind: "box" (a closed box filled with fluid compressed to (1/packing)^d rho0, gravity,
    viscosity, random velocities), "droplet" (a free droplet, Morton reordering and a fresh
    neighbour search every step) or "clamp" (a box with a column of particles started outside
    it, moving out: the first step clamps them in)."""
    rng = np.random.default_rng(seed)
    s = SPACING
    size = np.array([0.16, 0.12, 0.1][:d])
    g = [0.0, -9.81, 0.0][:d]
    common = dict(method="wcsph", viscosity=2e-3, gravity=g, speed_of_sound=20.0)
    if kind in ("droplet", "defaults"):
        x = km.sph.block(np.zeros(d), size, 0.95 * s)
        x += rng.uniform(-0.1 * s, 0.1 * s, x.shape)
        v = rng.normal(0, 0.3, x.shape)
        if kind == "defaults":  # Verlet lists with a skin, reordered at a rebuild 16 steps on
            return km.sph.Fluid(x, s, velocity=v, **common)
        return km.sph.Fluid(x, s, velocity=v, reorder_every=1, neighbor_skin=0.0, **common)
    x = km.sph.block(np.zeros(d), size, packing * s)
    size = x.max(0) + packing * s / 2  # the box the lattice fills
    x += rng.uniform(-0.1 * s, 0.1 * s, x.shape)
    x = np.clip(x, 0.2 * s, size - 0.2 * s)
    v = rng.normal(0, 0.3, x.shape)
    if kind == "clamp":
        # the last column, moved out beyond the reach of the walls' samples (2.5 spacings) and
        # moving out, but for two particles moving back in
        out = x[:, 0] > x[:, 0].max() - 0.3 * s
        x[out, 0] = size[0] + 4.5 * s
        v[out, 0] = np.abs(v[out, 0]) + 0.2
        v[np.flatnonzero(out)[:2], 0] = -0.3  # moving back in: their v is kept
    return km.sph.Fluid(x, s, velocity=v, domain=(np.zeros(d), size), reorder_every=0, **common)


def _order(before, after):
    """order[k] = the row of `before` holding the particle of row k of `after`."""
    row_of = np.empty(len(before["ids"]), np.int64)
    row_of[before["ids"]] = np.arange(len(before["ids"]))
    return row_of[after["ids"]]


def _magnitudes(sim, before, after):
    """A_i (module docstring) of the step before -> after, by particle id."""
    d, h, m, nu = sim.dim, sim.support_radius, sim.mass, sim.viscosity
    k = _order(before, after)
    x = before["x"][k]
    v = before["v"][k]
    rho = after["density"]
    P = after["pressure"] / rho ** 2
    pairs = km.sph.neighbor_pairs(x, h)
    i, j = pairs[:, 0], pairs[:, 1]
    xij, vij = x[i] - x[j], v[i] - v[j]
    r = np.linalg.norm(xij, axis=1)
    grad = np.abs(km.sph.kernel(r, h, d, derivative=1))
    s = np.abs(np.einsum("ij,ij->i", vij, xij)) / (r * r + 0.01 * h * h)
    visc = 2 * (d + 2) * nu * s * grad
    A = np.zeros(sim.n)
    np.add.at(A, i, m * np.abs(P[i] + P[j]) * grad + visc * m / rho[j])
    np.add.at(A, j, m * np.abs(P[i] + P[j]) * grad + visc * m / rho[i])
    by_id = np.empty(sim.n)
    by_id[after["ids"]] = A
    return by_id


def _walls(sim, x):
    """The domain walls' samples xb, volumes psi, the kernel values W_ib (n, M) and gradient
    factors (dW/dr / r)_ib of the particles at x, and the walls' densities
    rho_b = sum_k psi_k W_bk + sum_i m W_ib (solver.cpp, "WCSPH's walls")."""
    d, h, m = sim.dim, sim.support_radius, sim.mass
    xb = km.sph.box_boundary(*sim.domain, sim.spacing, 2)
    psi = sim.boundary_psi
    rb = np.linalg.norm(x[:, None, :] - xb[None], axis=2)
    near = rb < h
    wb = np.where(near, km.sph.kernel(rb, h, d), 0)
    fb = np.where(near & (rb > 0), km.sph.kernel(rb, h, d, derivative=1) / np.where(rb > 0, rb, 1), 0)
    rbb = np.linalg.norm(xb[:, None, :] - xb[None], axis=2)
    rho_b = (psi[None] * km.sph.kernel(rbb, h, d)).sum(1) + m * wb.sum(0)
    return xb, psi, wb, fb, rho_b


def _wall_margin(sim, x, direction, e):
    """min over the walls' samples of |rho_b - rho0| minus a bound of the change of rho_b when
    the particles move from x to x +- e direction: |sum_i m grad W_ib . e r_i| to first order plus
    sum_i m L |e r_i|^2 / 2 for the particles within h + e |r_i| (L = 12 sigma / h^2 bounds the
    cubic spline's Hessian, Taylor's remainder). Positive: no sample's density crosses rho0
    (Tait's kink) within the step, so the difference measures the derivative."""
    d, h, m = sim.dim, sim.support_radius, sim.mass
    xb, _, _, fb, rho_b = _walls(sim, x)
    grad = fb[:, :, None] * (x[:, None, :] - xb[None])  # grad_i W_ib (n, M, d)
    first = np.abs(m * np.einsum("ibk,ik->b", grad, e * direction))
    step = e * np.linalg.norm(direction, axis=1)
    reach = np.linalg.norm(x[:, None, :] - xb[None], axis=2) < h + step[:, None]
    sigma = {2: 40 / (7 * np.pi * h * h), 3: 8 / (np.pi * h ** 3)}[d]
    second = (m * 12 * sigma / h ** 2 * reach * (step ** 2 / 2)[:, None]).sum(0)
    return float((np.abs(rho_b - sim.rho0) - first - second).min())


def _reference_step(sim, x, v, nu, forces, dt):
    """One WCSPH step of `sim`'s scene written out in NumPy in double precision (brute-force
    boundary pairs; arrays by particle id): the step of solver.cpp without its single-precision
    kernel gradients. Returns x', v' and the densities of the step."""
    d, h, m, rho0, gamma = sim.dim, sim.support_radius, sim.mass, sim.rho0, sim.config.gamma
    B = rho0 * sim.speed_of_sound ** 2 / gamma
    pairs = km.sph.neighbor_pairs(x, h)
    i, j = pairs[:, 0], pairs[:, 1]
    xij, vij = x[i] - x[j], v[i] - v[j]
    r = np.linalg.norm(xij, axis=1)
    g = (km.sph.kernel(r, h, d, derivative=1) / r)[:, None] * xij
    rho = np.full(len(x), m * km.sph.kernel(0.0, h, d))
    w = m * km.sph.kernel(r, h, d)
    np.add.at(rho, i, w)
    np.add.at(rho, j, w)
    Bsum = np.zeros_like(x)
    wall_force = np.zeros_like(x)
    tait = lambda r: np.where(r > rho0, B * ((r / rho0) ** gamma - 1), 0.0) / r ** 2  # noqa: E731
    if sim.domain is not None:
        xb, psi, wb, fb, rho_b = _walls(sim, x)
        xib = x[:, None, :] - xb[None]
        rho += (psi[None] * wb).sum(1)
        Bsum = np.einsum("ib,ibk->ik", psi[None] * fb, xib)
        # The walls carry the pressure of their own density rho_b.
        wall_force = np.einsum("ib,ibk->ik", (psi * tait(rho_b))[None] * fb, xib)
    P = tait(rho)
    a = np.zeros_like(x) + sim.gravity + (0 if forces is None else forces / m)
    s = np.einsum("ij,ij->i", vij, xij) / (r * r + 0.01 * h * h)
    K = 2 * (d + 2) * nu
    np.add.at(a, i, (K * m / rho[j] * s - m * (P[i] + P[j]))[:, None] * g)
    np.add.at(a, j, (-K * m / rho[i] * s + m * (P[i] + P[j]))[:, None] * g)
    a -= P[:, None] * Bsum + wall_force
    v1 = v + dt * a
    x1 = x + dt * v1
    if sim.domain is not None:
        lo, hi = sim.domain
        below, above = x1 < lo, x1 > hi
        x1 = np.where(below, lo, np.where(above, hi, x1))
        v1 = np.where(below, np.maximum(v1, 0), np.where(above, np.minimum(v1, 0), v1))
    return x1, v1, rho


def _by_id(state, key):
    out = np.empty_like(state[key])
    out[state["ids"]] = state[key]
    return out


def _run(sim, s0, dt, controls, steps, override=None, nu=None, reference=False):
    """The run from s0 (with `override` state arrays and viscosity nu) by kinema's forward or
    by the NumPy reference, returning the final x, v by particle id (runs compare whatever the
    reordering) and the pattern of densities above rho0 at each step (the particles', then the
    walls': Tait's kink is in both)."""
    base_nu = sim.viscosity
    nu = base_nu if nu is None else nu
    above = []
    if reference:
        x, v = _by_id(s0, "x"), _by_id(s0, "v")
        override = override or {}
        x, v = override.get("x", x), override.get("v", v)
        for t in range(steps):
            walls = [] if sim.domain is None else [_walls(sim, x)[4] > sim.rho0]
            x, v, rho = _reference_step(sim, x, v, nu, None if controls is None else controls[t], dt)
            above.append(np.concatenate([rho > sim.rho0, *walls]))
        return {"x": x, "v": v}, np.array(above)
    sim.set_state(s0)
    sim._diff_set("viscosity", nu)
    for name, value in (override or {}).items():
        sim._diff_set(name, value)
    try:
        for t in range(steps):
            walls = [] if sim.domain is None else [_walls(sim, np.asarray(sim.x))[4] > sim.rho0]
            sim._diff_step(dt, None if controls is None else controls[t], {})
            compressed = np.empty(sim.n, bool)
            compressed[sim.ids] = sim.density > sim.rho0
            above.append(np.concatenate([compressed, *walls]))
    finally:
        sim._diff_set("viscosity", base_nu)
    return {k: _by_id(sim.state(), k) for k in NAMES}, np.array(above)


def _check(sim, steps, wrt, seed, where, rollout=True, reference=True):
    """Checks the gradients of `steps` steps from sim's state (a fresh scene: rows = ids)
    against central differences of the NumPy reference (reference=True; double rounding
    only) or of kinema's own forward (the single-precision bound of the module docstring)."""
    rng = np.random.default_rng(seed + 100)
    d, m = sim.dim, sim.mass
    controls = rng.normal(0, 2e-4, (steps, sim.n, d))
    s0 = sim.state()
    assert np.array_equal(s0["ids"], np.arange(sim.n)), "a fresh scene: rows are ids"
    W = {k: rng.normal(size=s0[k].shape) for k in NAMES}  # loss weights by particle id
    states = [s0]
    for t in range(steps):
        sim._diff_step(DT, controls[t], {})
        states.append(sim.state())
    last = states[-1]
    grad_after = {k: W[k][last["ids"]] for k in NAMES}  # rows of the last state
    sim.set_state(s0)
    if rollout:
        run = km.diff.rollout(sim, steps, DT, wrt=tuple(dict.fromkeys(wrt + ("controls",))), controls=controls)
        assert all(np.array_equal(run.outputs[k], last[k]) for k in NAMES), f"{where}: rollout differs from the run"
        grads = run.backward(grad_after)
    else:  # one step, as km.diff calls the protocol
        gb, gp, gc = sim._diff_step_adjoint(DT, s0, last, controls[0], grad_after, {})
        grads = dict(gb, **gp, controls=gc[None])
    delta_float = 0.0
    if not reference:
        lam = m * np.abs(grads["controls"])
        delta_float = sum(UF * float((lam[t].sum(1) * _magnitudes(sim, states[t], states[t + 1])).sum())
                          for t in range(steps))
    base_out, base_above = _run(sim, s0, DT, controls, steps, reference=reference)

    def loss_of(name):
        def loss(value):
            if name == "controls":
                out, above = _run(sim, s0, DT, value, steps, reference=reference)
            elif name == "viscosity":
                out, above = _run(sim, s0, DT, controls, steps, nu=value, reference=reference)
            else:
                out, above = _run(sim, s0, DT, controls, steps, {name: value}, reference=reference)
            crossed = np.argwhere(above != base_above)
            assert len(crossed) == 0, (f"{where}: particle {crossed[0][1]} crossed rho0 at step {crossed[0][0]} "
                                       f"in the difference for d/d{name}: choose another seed or step")
            return (float(sum((W[k] * out[k]).sum() for k in NAMES)),
                    float(sum((np.abs(W[k]) * np.abs(out[k])).sum() for k in NAMES)))
        return loss

    steps_of = STEPS_REFERENCE if reference else STEPS
    for name in wrt:
        base = {"controls": controls, "viscosity": sim.viscosity}.get(name, s0.get(name))
        direction = 1.0 if name == "viscosity" else rng.normal(size=np.shape(base))
        e = steps_of[name]
        if name == "x" and steps == 1 and sim.domain is not None:  # the step's walls are at x
            margin = _wall_margin(sim, s0["x"], direction, 2 * e)
            assert margin > 0, f"{where}: a wall sample's density lies within the step of rho0 ({margin:.3g})"

        def D(step, loss=loss_of(name)):
            lp, sp = loss(base + step * direction)
            lm, sm = loss(base - step * direction)
            return (lp - lm) / (2 * step), max(sp, sm)

        d1, scale = D(e)
        d2, _ = D(2 * e)
        delta = 1e3 * U * scale + delta_float
        bound = abs(d2 - d1) + 2 * delta / e
        got = float(np.sum(grads[name] * direction))
        assert abs(got - d1) <= bound, (
            f"{where}, d/d{name}: adjoint {got:.12g} vs central difference {d1:.12g} (|diff| {abs(got - d1):.3g} "
            f"> bound {bound:.3g}: truncation {abs(d2 - d1):.3g}, rounding {2 * delta / e:.3g}; D(2e) {d2:.12g})")
        informative = 1e-3 if reference else 5e-2
        assert bound <= informative * abs(d1), (f"{where}, d/d{name}: bound {bound:.3g} is not small against "
                                                f"|D| = {abs(d1):.3g}")


ALL = ("x", "v", "controls", "viscosity")


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kind", ["box", "droplet", "clamp"])
def test_reference_step_matches_the_forward(d, kind):
    """The NumPy reference is the step kinema runs: equal to the forward within the bound of its
    single-precision kernel gradients, |dv_i| <= dt (2^-24 + 200 u) A_i + 4 u |v_i'| and
    |dx_i| <= dt |dv_i| + 4 u |x_i'|, a bound far below the step's own change of v."""
    sim = _scene(d, kind, seed=d + 7)
    s0 = sim.state()
    f = np.random.default_rng(d).normal(0, 2e-4, (sim.n, d))
    x1, v1, rho = _reference_step(sim, s0["x"], s0["v"], sim.viscosity, f, DT)
    sim._diff_step(DT, f, {})
    s1 = sim.state()
    A = _magnitudes(sim, s0, s1)
    dv_bound = DT * (UF + 200 * U) * A + 4 * U * np.linalg.norm(v1, axis=1)
    dv = np.linalg.norm(_by_id(s1, "v") - v1, axis=1)
    dx = np.linalg.norm(_by_id(s1, "x") - x1, axis=1)
    assert np.allclose(_by_id(s1, "density"), rho, rtol=1e-13, atol=0)
    worst = np.argmax(dv / dv_bound)
    assert (dv <= dv_bound).all(), f"{d}D {kind}: particle {worst}: |dv| {dv[worst]:.3g} > bound {dv_bound[worst]:.3g}"
    assert (dx <= DT * dv_bound + 4 * U * np.linalg.norm(x1, axis=1)).all()
    assert dv_bound.sum() <= 1e-4 * np.linalg.norm(v1 - s0["v"], axis=1).sum()


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kind", ["box", "droplet", "clamp"])
def test_one_step_adjoint_matches_central_differences(d, kind):
    """Against the double-precision reference (tight), and for the box and clamp scenes against
    kinema's forward as run (the single-precision bound: its differences need a step of 1e-5 m,
    which in a droplet moves some surface particle across rho0). WCSPH's walls carry the
    pressure of their own density, so the step of x must leave every wall sample's density on
    its side of rho0 (_wall_margin, asserted in _check); the steps of v, the controls and the
    viscosity leave the step's positions, hence the walls' densities, as they are. The 3D boxes
    packed at 0.95 spacings put some wall sample within the step of x of rho0 (in every one of
    40 directions tried); packed at 0.9 (compressed to 1.37 rho0) none (margin 0.07-0.11
    kg/m^3 beyond the step's bound), so their x is checked there, where the larger pressures'
    single-precision rounding leaves the difference in v at its step uninformative (bound 0.3
    |D|), and the rest at 0.95."""
    _check(_scene(d, kind, seed=d + 7), 1, ALL, seed=d, where=f"{d}D {kind}, one step", rollout=False)
    if kind == "droplet":
        return
    where = f"{d}D {kind}, one step as run"
    if d == 2:
        _check(_scene(d, kind, seed=d + 7), 1, ALL, seed=d + 47, where=where, rollout=False, reference=False)
    else:
        _check(_scene(d, kind, seed=d + 7, packing=0.9), 1, ("x",), seed=d + 47, where=where, rollout=False,
               reference=False)
        _check(_scene(d, kind, seed=d + 7), 1, ("v", "controls", "viscosity"), seed=d + 47, where=where,
               rollout=False, reference=False)


def test_scenes_take_the_branches_they_test():
    """The box is compressed everywhere (Tait's p > 0 branch), the droplet has expanded
    particles (p = 0) and reorders its rows, the clamp scene's first step clamps."""
    box = _scene(2, "box")
    box.step(DT)
    assert (box.density > box.rho0).mean() > 0.9, box.density.min()
    assert len(box.neighbor_pairs()[1]) > box.n
    drop = _scene(2, "droplet")
    drop.step(DT)
    assert (drop.density < drop.rho0).sum() > 5 and (drop.density > drop.rho0).sum() > 5
    assert not np.array_equal(drop.ids, np.arange(drop.n))
    clamp = _scene(2, "clamp")
    clamp.step(DT)
    wall = clamp.x[:, 0] == clamp.domain[1][0]
    assert wall.sum() >= 3 and (clamp.v[wall, 0] == 0).sum() >= 3 and (clamp.v[wall, 0] < 0).sum() >= 1


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kind", ["box", "droplet"])
def test_rollout_gradients_match_central_differences(d, kind):
    sim = _scene(d, kind, seed=10 + d)
    _check(sim, 4, ALL, seed=20 + d, where=f"{d}D {kind}, four-step rollout")


def test_rollout_with_default_neighbour_lists_and_reordering():
    """100 steps with the default Verlet skin (lists kept over several steps) and Morton
    reordering at a rebuild at least 16 steps after the last: the adjoint's fresh pair search
    and the ids still give the derivative of the run."""
    sim = _scene(2, "defaults", seed=30)
    steps = 100
    run_ids = []
    sim.set_state(sim.state())
    s0 = sim.state()
    for _ in range(steps):
        sim._diff_step(DT, None, {})
        run_ids.append(sim.ids.copy())
    assert not np.array_equal(run_ids[-1], run_ids[0]), "the run was expected to reorder its rows"
    sim.set_state(s0)
    _check(sim, steps, ALL, seed=31, where="2D droplet, default lists, 100 steps")


def test_checkpointed_backward_equals_stored():
    sim = _scene(2, "droplet", seed=3)
    rng = np.random.default_rng(4)
    steps = 9
    controls = rng.normal(0, 1e-4, (steps, sim.n, 2))
    s0 = sim.state()
    stored = km.diff.rollout(sim, steps, DT, wrt=ALL, controls=controls)
    g = {k: rng.normal(size=stored.outputs[k].shape) for k in NAMES}
    a = stored.backward(g)
    sim.set_state(s0)
    check = km.diff.rollout(sim, steps, DT, wrt=ALL, controls=controls, checkpoints=3)
    b = check.backward(g)
    assert check.peak_states <= 4 and check.recomputed_steps > 0
    for k in ALL:
        assert np.array_equal(a[k], b[k]), f"checkpointed d/d{k} differs from stored"


def test_adjoint_is_deterministic_across_thread_counts():
    sim = _scene(3, "droplet", seed=5)
    s0 = sim.state()
    sim._diff_step(DT, None, {})
    s1 = sim.state()
    g = {k: np.random.default_rng(1).normal(size=s1[k].shape) for k in NAMES}
    threads = km.get_num_threads()
    try:
        results = []
        for n in (1, 2):
            km.set_num_threads(n)
            results.append(sim._diff_step_adjoint(DT, s0, s1, None, g, {}))
    finally:
        km.set_num_threads(threads)
    (a, pa, _), (b, pb, _) = results
    assert all(np.array_equal(a[k], b[k]) for k in NAMES) and pa == pb


def test_torch_bridge_through_an_sph_rollout():
    torch = pytest.importorskip("torch")
    sim = _scene(2, "droplet", seed=7)
    s0 = sim.state()
    v0 = torch.tensor(s0["v"], requires_grad=True)
    nu = torch.tensor(sim.viscosity, dtype=torch.float64, requires_grad=True)
    out = km.torch.rollout(sim, 3, DT, inputs={"v": v0, "viscosity": nu})
    loss = (out["x"] ** 2).sum()
    loss.backward()
    sim.set_state(s0)
    run = km.diff.rollout(sim, 3, DT, wrt=("v", "viscosity"))
    ref = run.backward({"x": 2 * run.outputs["x"]})
    assert np.allclose(v0.grad.numpy(), ref["v"], rtol=1e-12, atol=0)
    assert abs(nu.grad.item() - ref["viscosity"]) <= 1e-12 * abs(ref["viscosity"])


def test_refusals_name_the_argument():
    x = km.sph.block([0, 0], [0.1, 0.1], SPACING)
    dfsph = km.sph.Fluid(x, SPACING)
    with pytest.raises(ValueError, match="method"):
        km.diff.rollout(dfsph, 2, 1e-3, wrt=("v",))
    sim = km.sph.Fluid(x, SPACING, method="wcsph", speed_of_sound=20.0)
    with pytest.raises(ValueError, match="cfl"):
        km.diff.rollout(sim, 2, 1e-4, wrt=("v",), cfl=0.4)
    with pytest.raises(ValueError, match="wrt"):
        km.diff.rollout(sim, 2, 1e-4, wrt=("density",))
    with pytest.raises(ValueError, match="controls"):
        km.diff.rollout(sim, 2, 1e-4, wrt=("controls",), controls=np.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="viscosity"):
        sim._diff_set("viscosity", -1.0)
    assert sim.viscosity == 0.0  # a refused viscosity changes nothing
    s0 = sim.state()
    sim._diff_step(1e-4, None, {})
    s1 = sim.state()
    bad = dict(s1, ids=np.zeros_like(s1["ids"]))
    with pytest.raises(ValueError, match="ids"):
        sim._diff_step_adjoint(1e-4, s0, bad, None, {"x": np.zeros_like(x), "v": np.zeros_like(x)}, {})
