"""Gradients of km.grid (Solver::step_adjoint and km.diff rollouts): the projection's transpose
on its own (dot-product test), and central finite differences of one step and of short runs for
every advection scheme (semi-Lagrangian, MacCormack and BFECC on the branch their clamp takes),
every Runge-Kutta order of the back-trace, 2D and 3D, and every differentiable input (u, v, w,
density, temperature, viscosity, per-step controls), with buoyancy, solids, open sides and a
periodic box.

Tolerance of a finite-difference check along a random direction r with step e: the central
difference D(e) = (L(p + e r) - L(p - e r)) / 2e has a truncation error c e^2 + O(e^4) and an
evaluation error at most 2 delta / 2e, where delta bounds the error of one evaluation of
L = <W, state>. Two sources: float64 rounding of the step's sums (each entry a sum of at most a
few hundred products: relative error below 1e3 u) and the iterative solves, which stop at a
relative residual tol = 1e-13 (pressure) and 1e-15 (viscosity); with the condition number of
the pressure operator below 150 on these grids (about 4 d (n / pi)^2 for n <= 12 cells per axis)
their relative error is below 150 tol. So delta <= (1e3 u + 150 tol) sum |W| |state|. The
truncation is measured: D(e) - D(2e) = -3 c e^2 + O(e^4), so |D(2e) - D(e)| bounds it three
times over. A check passes when |adjoint - D(e)| <= |D(2e) - D(e)| + 2 delta / e, and the bound
must be below 1e-2 |g| |r| / sqrt(n) (the size of <g, r> for a random r) to say anything.
"""

import functools

import numpy as np
import pytest

import kinema as km
from gradcheck import check_directional, step_adjoint_at_thread_counts

U = np.finfo(float).eps / 2
TOL = 1e-13
SOLVE = 150 * TOL  # relative error of one evaluation from the iterative solves (module docstring)
# Steps small enough that MacCormack's and BFECC's clamps rarely switch within 2e (a velocity
# step of 1e-4 switched some in these scenes); the evaluation error 2 delta / e stays below 1e-2 |D|.
STEPS = {"u": 1e-6, "v": 1e-6, "w": 1e-6, "density": 1e-5, "temperature": 1e-5, "viscosity": 1e-5,
         "controls": 1e-4}


def _fluid(shape, advection="maccormack", rk_order=2, *, viscosity=0.01, solid=False, seed=0, cfl=0.3,
           **options):
    """A fluid with a mean flow of `cfl` cells per step (dt = 0.02 in 2D, 0.03 in 3D) along every
    axis plus a smooth wave of random direction, smooth waves of density and temperature, buoyancy.

    The mean flow keeps the back-traced points away from the grid nodes, where the piecewise
    (bi/tri)linear interpolation has its kinks: the gradient is exact off the kinks, and a
    central difference straddling one has an O(1) relative error whatever its step. With a
    CFL number near 0.3 and a wave of 0.09 cells, every interior departure point lies more than
    0.1 cells from a node, far beyond what the difference steps move it (below 1e-5 cells).
    Fields without flat regions keep MacCormack's and BFECC's clamps to few nodes (near
    extrema): where a field is flat the clamp interval collapses and any perturbation switches
    the branch, which no difference step resolves."""
    rng = np.random.default_rng(seed)
    d = len(shape)
    sim = km.grid.Fluid(shape, 1.0 / shape[0], advection=advection, rk_order=rk_order, tol=TOL,
                        viscosity=viscosity, density=True, temperature=True, buoyancy=(0.5, 1.0),
                        **options)
    if solid:
        mask = np.zeros(shape, bool)
        mask[tuple(slice(n // 2 - 1, n // 2 + 1) for n in shape)] = True
        sim.solid = mask
    speed = cfl * sim.h / (0.02 if d == 2 else 0.03)
    for c, name in enumerate("uvw"[:d]):
        a = getattr(sim, name)
        x = [np.arange(n) * sim.h for n in a.shape]
        x[c] = x[c] - 0.5 * sim.h
        x = np.stack(np.meshgrid(*x, indexing="ij"), -1)
        k, phase = rng.normal(0.0, 3.0, d), rng.uniform(0, 2 * np.pi)
        a[...] = speed * (1 + 0.3 * np.sin(x @ k + phase))
    c = sim.cell_centers()
    sim.density = 0.5 + 0.4 * np.sin(c @ rng.normal(0.0, 6.0, d) + rng.uniform(0, 2 * np.pi))
    sim.temperature = np.cos(c @ rng.normal(0.0, 6.0, d))
    return sim


def _loss(sim, state, weights, dt, controls, steps, override=None, viscosity=None):
    """L = <W, state after `steps`> from `state` with one input replaced; also sum |W| |state|."""
    sim.set_state(state)
    nu = sim.viscosity
    if viscosity is not None:
        sim._diff_set("viscosity", viscosity)
    for name, value in (override or {}).items():
        getattr(sim, name)[...] = value
    try:
        for k in range(steps):
            sim._diff_step(dt, None if controls is None else controls[k], {})
    finally:
        sim._diff_set("viscosity", nu)
    out = {n: getattr(sim, n) for n in weights}
    return (sum(float(np.sum(weights[n] * out[n])) for n in weights),
            sum(float(np.sum(np.abs(weights[n] * out[n]))) for n in weights))


# the bound of the module docstring; informative when below 1e-2 |g| |r| / sqrt(n)
_fd_check = functools.partial(check_directional, rounding=1e3 * U + SOLVE, typical=1e-2)


def _check_run(sim, steps, dt, names=None, seed=1, where=""):
    """Every differentiable input of `sim` against central differences over `steps` steps."""
    rng = np.random.default_rng(seed)
    state_names = sim._diff_state_names
    controls = rng.normal(0.0, 1.0, (steps,) + sim._diff_control_shape())
    weights = {n: rng.normal(size=getattr(sim, n).shape) for n in state_names}
    names = names or state_names + ("viscosity", "controls")
    s0 = sim.state()
    run = km.diff.rollout(sim, steps, dt, wrt=names, controls=controls)
    grads = run.backward(weights)
    for name in names:
        here = f"{where} d/d{name}"
        if name in state_names:
            base = s0[name]
            _fd_check(lambda p: _loss(sim, s0, weights, dt, controls, steps, {name: p}), base,
                      rng.normal(size=base.shape), grads[name], STEPS[name], here)
        elif name == "viscosity":
            nu = sim.viscosity
            _fd_check(lambda p: _loss(sim, s0, weights, dt, controls, steps, viscosity=float(p[0])),
                      np.array([nu]), np.ones(1), np.array([grads[name]]), STEPS[name], here)
        else:
            _fd_check(lambda p: _loss(sim, s0, weights, dt, p, steps), controls,
                      rng.normal(size=controls.shape), grads[name], STEPS[name], here)


# ----------------------------------------------------------------------------- projection

def _projection_pair(sim, shape, case):
    """Solids for `case`, and random MAC fields a (set as the velocity) and b: (names, a, b, rng)."""
    if "solid" in case:
        mask = np.zeros(shape, bool)
        mask[tuple(slice(2, 5) if max(shape) < 20 else slice(5, 11) for _ in shape)] = True
        sim.solid = mask
        sim.step(1e-9)  # the solver builds its solid faces at a step
    rng = np.random.default_rng(3)
    names = "uvw"[:len(shape)]
    a = {n: rng.normal(size=getattr(sim, n).shape) for n in names}
    b = {n: rng.normal(size=getattr(sim, n).shape) for n in names}
    for n in names:
        getattr(sim, n)[...] = a[n]
    return names, a, b, rng


@pytest.mark.parametrize("shape", [(16, 12), (8, 6, 10)])
@pytest.mark.parametrize("case", ["closed", "solid", "open_solid", "periodic"])
def test_projection_adjoint_is_its_transpose(shape, case):
    """<P a, b> = <a, P^T b> for random MAC fields a, b, to rounding and the solve's tolerance."""
    options = {"periodic": {"boundary": "periodic"}, "open_solid": {"open": ("x+", "y-")}}.get(case, {})
    sim = km.grid.Fluid(shape, 0.1, tol=TOL, **options)
    names, a, b, _ = _projection_pair(sim, shape, case)
    sim.pressure[...] = 0
    dt = 0.05
    sim._core.project(dt)
    pt_b = sim._core.projection_adjoint(dt, b)
    lhs = sum(float(np.sum(getattr(sim, n) * b[n])) for n in names)
    rhs = sum(float(np.sum(a[n] * pt_b[n])) for n in names)
    # each side: a sum of ~1e3 products of O(1) terms (rounding 1e3 u per term) plus the
    # projection's error from the solve, relative 1e3 tol (module docstring)
    size = sum(np.sqrt(np.sum(a[n] ** 2) * np.sum(b[n] ** 2)) for n in names)
    bound = (1e3 * U + 1e3 * TOL) * size
    assert abs(lhs - rhs) <= bound, f"{case} {shape}: <Pa, b> {lhs!r} vs <a, P^T b> {rhs!r} (bound {bound:.3g})"
    # P is a projection and not the identity: the test exercises the solve
    assert abs(lhs - sum(float(np.sum(a[n] * b[n])) for n in names)) > 1e3 * bound


# -------------------------------------------------------------- finite differences: 2D

@pytest.mark.parametrize("advection", ["semi_lagrangian", "maccormack", "bfecc"])
@pytest.mark.parametrize("rk_order", [1, 2, 3])
def test_one_step_2d_matches_finite_differences(advection, rk_order):
    sim = _fluid((12, 10), advection, rk_order)
    _check_run(sim, 1, 0.02, where=f"2D {advection} rk{rk_order} one step")


@pytest.mark.parametrize("advection", ["semi_lagrangian", "maccormack", "bfecc"])
def test_short_run_2d_matches_finite_differences(advection):
    sim = _fluid((12, 10), advection, 2, solid=True, open=("y+",), gravity=(0.0, -1.0))
    _check_run(sim, 4, 0.02, where=f"2D {advection} 4 steps, solid and open side")


def test_periodic_run_matches_finite_differences():
    sim = _fluid((12, 10), "maccormack", 3, boundary="periodic")
    _check_run(sim, 3, 0.02, where="2D periodic")


def test_inviscid_run_matches_finite_differences():
    """nu = 0: the forward pass skips the viscous solve; dL/dnu there is still the derivative."""
    sim = _fluid((12, 10), "semi_lagrangian", 2, viscosity=0.0)
    _check_run(sim, 2, 0.02, names=("u", "v", "density", "controls"), where="2D inviscid")
    s0 = sim.state()
    rng = np.random.default_rng(4)
    weights = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    grads = km.diff.rollout(sim, 2, 0.02, wrt=("viscosity",)).backward(weights)
    e = 1e-6  # one-sided: nu >= 0; its error e * |L''| is measured by the step 2e
    d1 = (_loss(sim, s0, weights, 0.02, None, 2, viscosity=e)[0] - _loss(sim, s0, weights, 0.02, None, 2)[0]) / e
    d2 = (_loss(sim, s0, weights, 0.02, None, 2, viscosity=2 * e)[0] - _loss(sim, s0, weights, 0.02, None, 2)[0]) / (2 * e)
    bound = 2 * abs(d2 - d1) + 1e-6 * abs(d1)
    assert abs(grads["viscosity"] - d1) <= bound, (grads["viscosity"], d1, d2)


# -------------------------------------------------------------- finite differences: 3D

@pytest.mark.parametrize("advection,rk_order", [("semi_lagrangian", 1), ("maccormack", 2), ("bfecc", 3)])
def test_one_step_3d_matches_finite_differences(advection, rk_order):
    sim = _fluid((6, 5, 7), advection, rk_order)
    _check_run(sim, 1, 0.03, where=f"3D {advection} rk{rk_order} one step")


def test_short_run_3d_matches_finite_differences():
    sim = _fluid((6, 5, 7), "maccormack", 2, solid=True, open=("z+",))
    _check_run(sim, 3, 0.03, where="3D MacCormack 3 steps, solid and open side")


@pytest.mark.parametrize("shape", [(16, 12), (8, 6, 7)])
@pytest.mark.parametrize("advection", ["maccormack", "bfecc"])
def test_clamped_nodes_match_finite_differences(shape, advection):
    """A rough (random) density makes the clamp take a bound at many nodes, whose gradient goes
    to the extreme node of the forward stencil (MacCormack: found by the last adjoint pass,
    which traces that stencil again). A clamped node's value is a value of the density before
    the step, exactly: that shows the clamps are taken. Random values keep the clamp margins
    O(0.1), far beyond what the difference steps move them."""
    sim = _fluid(shape, advection, 2)
    rough = np.random.default_rng(9).uniform(0.0, 1.0, shape)
    sim.density = rough
    dt = 0.02 if len(shape) == 2 else 0.03
    s0 = sim.state()
    sim._diff_step(dt, None, {})
    clamped = np.count_nonzero(np.isin(sim.density, rough))
    assert clamped >= 0.01 * rough.size, f"only {clamped} of {rough.size} nodes clamped"
    sim.set_state(s0)
    _check_run(sim, 1, dt, names=("density", "u", "controls"), where=f"{len(shape)}D {advection} clamped")


@pytest.mark.parametrize("advection,rk_order", [("semi_lagrangian", 1), ("maccormack", 2), ("bfecc", 3)])
def test_one_cell_thick_matches_finite_differences(advection, rk_order):
    """One cell along y: the row-wise back-traces (advect_rows) need two, so the adjoint traces
    node by node; the same checks. v is pinned by the walls (its gradient is 0): left out. (A 2D
    channel one cell thick is no test: its divergence-free velocity is 0.)"""
    sim = _fluid((6, 1, 7), advection, rk_order)
    names = tuple(n for n in sim._diff_state_names if n != "v") + ("viscosity", "controls")
    _check_run(sim, 2, 0.03, names=names, where=f"3D one cell thick {advection} rk{rk_order}")


# ---------------------------------------------------------------- rollouts and refusals

def test_checkpointed_equals_stored_and_repeatable():
    sim = _fluid((12, 10), "bfecc", 2)
    s0 = sim.state()
    rng = np.random.default_rng(5)
    steps = 9
    controls = rng.normal(0, 1, (steps,) + sim._diff_control_shape())
    weights = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    wrt = sim._diff_state_names + ("viscosity", "controls")
    stored = km.diff.rollout(sim, steps, 0.02, wrt=wrt, controls=controls)
    g1 = stored.backward(weights)
    g2 = stored.backward(weights)
    sim.set_state(s0)
    g3 = km.diff.rollout(sim, steps, 0.02, wrt=wrt, controls=controls, checkpoints=3).backward(weights)
    for name in wrt:
        np.testing.assert_array_equal(g1[name], g2[name], err_msg=name)
        np.testing.assert_array_equal(g1[name], g3[name], err_msg=name)


@pytest.mark.parametrize("advection,rk_order", [("semi_lagrangian", 1), ("maccormack", 2), ("bfecc", 3)])
def test_gradients_without_viscosity_equal_those_with_it(advection, rk_order):
    # Without dL/dnu wanted, each step's adjoint recomputes only the advection passes it reads,
    # and a run stored whole is reversed in C++ (_diff_record): the other gradients must be the
    # same bits as with dL/dnu and as the step-by-step (checkpointed) path.
    sim = _fluid((12, 10), advection, rk_order)
    s0 = sim.state()
    rng = np.random.default_rng(6)
    steps = 5
    controls = rng.normal(0, 1, (steps,) + sim._diff_control_shape())
    weights = {n: rng.normal(size=getattr(sim, n).shape) for n in sim._diff_state_names}
    names = sim._diff_state_names + ("controls",)
    runs = []
    for wrt, checkpoints in ((names + ("viscosity",), None), (names, None), (names, 2)):
        sim.set_state(s0)
        runs.append(km.diff.rollout(sim, steps, 0.02, wrt=wrt, controls=controls,
                                    checkpoints=checkpoints).backward(weights))
    for name in names:
        assert np.any(runs[0][name] != 0), name
        for other in runs[1:]:
            np.testing.assert_array_equal(runs[0][name], other[name], err_msg=name)


@pytest.mark.parametrize("shape,advection,rk_order", [((192, 176), "maccormack", 2), ((34, 32, 32), "bfecc", 3)])
def test_adjoint_is_the_same_for_any_thread_count(shape, advection, rk_order):
    # Large enough that every scatter runs in parallel (more than 32768 nodes, several
    # blocks of twice the back-traces' reach): the adjoint's scatters order each node's terms by
    # block and row, never by thread, so 1, 2 and 3 threads give the same bits.
    sim = _fluid(shape, advection, rk_order)
    dt = 0.02 if len(shape) == 2 else 0.03
    control = np.random.default_rng(7).normal(0, 1, sim._diff_control_shape())
    results = step_adjoint_at_thread_counts(sim, dt, control, 8, (1, 2, 3))
    first = results[0]
    for other in results[1:]:
        for name in sim._diff_state_names:
            np.testing.assert_array_equal(first[0][name], other[0][name], err_msg=name)
        assert first[1]["viscosity"] == other[1]["viscosity"]
        np.testing.assert_array_equal(first[2], other[2])


def test_outputs_equal_plain_steps():
    sim = _fluid((12, 10), "maccormack", 2)
    s0 = sim.state()
    run = km.diff.rollout(sim, 3, 0.02, wrt=("u",))
    sim.set_state(s0)
    for _ in range(3):
        sim.step(0.02)
    for name in sim._diff_state_names:
        np.testing.assert_array_equal(run.outputs[name], getattr(sim, name), err_msg=name)


def test_refusals_name_the_option():
    sim = km.grid.Fluid((8, 8), 0.1, vorticity_confinement=0.3)
    with pytest.raises(ValueError, match="vorticity_confinement"):
        km.diff.rollout(sim, 1, 0.01, wrt=("u",))
    sim = km.grid.Fluid((8, 8), 0.1, walls="no_slip")
    with pytest.raises(ValueError, match="walls"):
        km.diff.rollout(sim, 1, 0.01, wrt=("u",))
    sim = km.grid.Fluid((8, 8), 0.1)
    sim.set_wall_velocity("y+", (1.0, 0.0))
    with pytest.raises(ValueError, match="walls"):
        km.diff.rollout(sim, 1, 0.01, wrt=("u",))
    sim = km.grid.Fluid((8, 8), 0.1)
    with pytest.raises(ValueError, match="density"):
        km.diff.rollout(sim, 1, 0.01, wrt=("density",))
    with pytest.raises(ValueError, match="cfl"):
        km.diff.rollout(sim, 1, 0.01, wrt=("u",), cfl=1.0)
    with pytest.raises(ValueError, match="control"):
        km.diff.rollout(sim, 1, 0.01, wrt=("u",), controls=np.zeros((1, 8, 8, 3)))


def test_torch_bridge_matches_rollout():
    torch = pytest.importorskip("torch")
    import kinema.torch as kt

    sim = _fluid((10, 8), "semi_lagrangian", 2)
    s0 = sim.state()
    rng = np.random.default_rng(6)
    weights = rng.normal(size=sim.density.shape)
    grads = km.diff.rollout(sim, 2, 0.02, wrt=("density", "viscosity")).backward({"density": weights})
    sim.set_state(s0)
    rho = torch.tensor(s0["density"], requires_grad=True)
    nu = torch.tensor(sim.viscosity, dtype=torch.float64, requires_grad=True)
    out = kt.rollout(sim, 2, 0.02, {"density": rho, "viscosity": nu})
    (out["density"] * torch.from_numpy(weights)).sum().backward()
    np.testing.assert_allclose(rho.grad.numpy(), grads["density"], rtol=1e-12, atol=1e-14)
    assert nu.grad.item() == pytest.approx(grads["viscosity"], rel=1e-12)


def test_sources_match_finite_differences():
    """A density emitter and a velocity inflow impose values before every step: the gradient
    with respect to what they overwrite is zero, the rest flows around them."""
    sim = _fluid((12, 10), "semi_lagrangian", 2, open=("y+",))
    region = np.zeros(sim.shape, bool)
    region[4:7, 0:2] = True
    sim.add_source(region, density=1.0, velocity=(0.0, 1.5))
    _check_run(sim, 3, 0.02, names=("u", "v", "density", "controls"), where="2D with sources")
    grads = km.diff.rollout(sim, 2, 0.02, wrt=("density",)).backward(
        {"density": np.ones(sim.shape)})
    assert np.all(grads["density"][region] == 0)


# ------------------------------------------------- fixed V-cycle projection (pressure_vcycles)
# Grids large enough for a hierarchy of at least two levels (the multigrid coarsens while a
# level has more than 512 cells, and solves the coarsest exactly), so the cycles smooth, restrict
# and prolong and are not one direct solve.
VCYCLE_SHAPES = [(64, 48), (16, 12, 20)]


@pytest.mark.parametrize("shape", VCYCLE_SHAPES)
@pytest.mark.parametrize("case", ["closed", "solid", "open_solid", "periodic"])
@pytest.mark.parametrize("cycles", [1, 3])
def test_vcycle_projection_adjoint_is_its_transpose(shape, case, cycles):
    """k V-cycles from zero are a fixed linear map of the divergence; the adjoint runs the same
    cycles: <P a, b> = <a, P^T b> to rounding alone (no solve tolerance enters)."""
    options = {"periodic": {"boundary": "periodic"}, "open_solid": {"open": ("x+", "y-")}}.get(case, {})
    sim = km.grid.Fluid(shape, 0.1, pressure_vcycles=cycles, **options)
    assert sim._core.multigrid_levels() >= 2
    names, a, b, rng = _projection_pair(sim, shape, case)
    sim.pressure[...] = rng.normal(size=sim.shape)  # ignored: the cycles start from zero
    dt = 0.05
    info = sim._core.project(dt)
    pt_b = sim._core.projection_adjoint(dt, b)
    lhs = sum(float(np.sum(getattr(sim, n) * b[n])) for n in names)
    rhs = sum(float(np.sum(a[n] * pt_b[n])) for n in names)
    # each side: sums of ~1e4 products, rounding below 1e4 u per unit of |a| |b| (the cycles'
    # own rounding, amplified by at most the operator's condition number times u, is smaller)
    size = sum(np.sqrt(np.sum(a[n] ** 2) * np.sum(b[n] ** 2)) for n in names)
    bound = 1e4 * U * size
    assert abs(lhs - rhs) <= bound, f"{case} {shape}: <Pa, b> {lhs!r} vs <a, P^T b> {rhs!r} (bound {bound:.3g})"
    assert abs(lhs - sum(float(np.sum(a[n] * b[n])) for n in names)) > 1e3 * bound
    # not converged (a random field is far from smooth): the reported divergence is what is left
    assert info.iterations == cycles and 1e-8 < info.residual < 1


@pytest.mark.parametrize("shape", VCYCLE_SHAPES)
def test_vcycle_residual_is_the_divergence_left(shape):
    """StepStats.pressure.residual = ||div u after|| / ||div u before||; it falls with the cycle
    count by at least the multigrid's convergence factor (below 0.5 per cycle here), and the
    state's initial pressure plays no part. A periodic box: a random field there is a valid
    velocity (no wall faces to pin, its divergence sums to zero)."""
    rng = np.random.default_rng(8)
    fields = None
    left = []
    for cycles in (1, 2, 4):
        sim = km.grid.Fluid(shape, 1.0 / shape[0], pressure_vcycles=cycles, boundary="periodic")
        if fields is None:
            fields = {n: rng.normal(size=getattr(sim, n).shape) for n in "uvw"[:len(shape)]}
            for c, f in enumerate(fields.values()):  # the duplicate last face holds face 0's value
                np.moveaxis(f, c, 0)[-1] = np.moveaxis(f, c, 0)[0]
        for n, f in fields.items():
            getattr(sim, n)[...] = f
        before = np.linalg.norm(sim.divergence())
        sim.pressure[...] = rng.normal(size=sim.shape)
        stats = sim._core.project(0.1)
        after = np.linalg.norm(sim.divergence())
        assert stats.residual == pytest.approx(after / before, rel=1e-8)
        left.append(stats.residual)
    assert left[1] < 0.5 * left[0] and left[2] < 0.25 * left[1], left
    # and the converged projection leaves 1e-6 of it by default
    sim = km.grid.Fluid(shape, 1.0 / shape[0], boundary="periodic")
    for n, f in fields.items():
        getattr(sim, n)[...] = f
    assert sim._core.project(0.1).residual <= 1e-6


def test_vcycle_runs_match_finite_differences():
    """The gradient of runs with a fixed-cycle projection, 2D (solid, open side) and 3D."""
    sim = _fluid((40, 32), "semi_lagrangian", 2, solid=True, open=("y+",), gravity=(0.0, -1.0),
                 pressure_vcycles=2)
    _check_run(sim, 3, 0.02, names=("u", "v", "density", "viscosity", "controls"), where="2D 2 V-cycles")
    sim = _fluid((12, 10, 14), "maccormack", 2, pressure_vcycles=1)
    _check_run(sim, 2, 0.03, names=("w", "temperature", "controls"), where="3D 1 V-cycle")


def test_vcycle_refusals_name_the_option():
    with pytest.raises(ValueError, match="pressure_vcycles"):
        km.grid.Fluid((8, 8), 0.1, pressure_vcycles=0)
    with pytest.raises(ValueError, match="pressure_vcycles"):
        km.grid.Fluid((8, 8), 0.1, pressure_vcycles=10**12)
    with pytest.raises(ValueError, match="pressure_vcycles"):
        km.grid.Fluid((8, 8), 0.1, pressure_vcycles=2, projection="cg")
    with pytest.raises(ValueError, match="pressure_vcycles"):
        km.grid.Fluid((9, 8), 0.1, pressure_vcycles=2, boundary="periodic")
