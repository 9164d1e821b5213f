"""km.diffusion: exact decay of discrete heat modes, the FTCS stability limit on both sides,
conservation, convergence order in time and space, and bad input."""

import math

import numpy as np
import pytest

import kinema as km


def centres(shape, h):
    return np.meshgrid(*[(np.arange(n) + 0.5) * h for n in shape], indexing="ij")


def mode(shape, h, bc, k=1):
    """A discrete eigenvector of A = -lap_h and its eigenvalue (cos modes are exact for the
    cell-centred Neumann operator, sin modes for the ghost = -u Dirichlet operator)."""
    X = centres(shape, h)
    lam = 0.0
    field = np.ones(shape)
    for x, n in zip(X, shape):
        L = n * h
        field = field * (np.cos(k * np.pi * x / L) if bc == "neumann" else np.sin(k * np.pi * x / L))
        lam += 4 / h**2 * math.sin(k * math.pi / (2 * n)) ** 2
    return field, lam


def growth(scheme, c, lam):
    if scheme == "ftcs":
        return 1 - c * lam
    if scheme == "implicit":
        return 1 / (1 + c * lam)
    return (1 - c * lam / 2) / (1 + c * lam / 2)


@pytest.mark.parametrize("shape", [(32, 24), (12, 10, 14)])
@pytest.mark.parametrize("bc", ["neumann", "dirichlet"])
@pytest.mark.parametrize("scheme", ["ftcs", "implicit", "crank_nicolson"])
def test_heat_mode_decays_exactly(shape, bc, scheme):
    h, kappa = 0.05, 0.7
    d = len(shape)
    dt = 0.9 * h**2 / (2 * d * kappa) if scheme == "ftcs" else 4e-3
    T0, lam = mode(shape, h, bc, k=2)
    steps = 5
    T = km.diffusion.step(T0, kappa, dt, h, scheme=scheme, bc=bc, steps=steps)
    expected = growth(scheme, kappa * dt, lam) ** steps * T0
    err = np.abs(T - expected).max()
    # Implicit solves stop at a relative residual of 1e-10 per step.
    assert err <= 1e-9 * np.abs(T0).max(), f"{scheme}/{bc}: max error {err:.3e}"


@pytest.mark.parametrize("d", [2, 3])
def test_ftcs_limit_on_both_sides(d):
    shape, h, kappa = (16,) * d, 0.1, 1.0
    limit = km.diffusion.stable_dt(h, kappa, d)
    assert limit == pytest.approx(h**2 / (2 * d * kappa), rel=1e-15)
    # The checkerboard is the stiffest mode: at the limit it flips sign but does not grow.
    checker = np.indices(shape).sum(axis=0) % 2 * 2.0 - 1
    T = km.diffusion.step(checker, kappa, limit, h, scheme="ftcs", bc="neumann", steps=50)
    assert np.abs(T).max() <= 1 + 1e-12
    with pytest.raises(km.StabilityError, match="dt <= "):
        km.diffusion.step(checker, kappa, limit * 1.01, h, scheme="ftcs")
    # Unchecked, just beyond the limit, the same mode grows: the limit is real.
    T = km.diffusion.step(checker, kappa, limit * 1.2, h, scheme="ftcs", steps=20, check=False)
    assert np.abs(T).max() > 2


def test_ftcs_blow_up_is_reported_not_returned():
    checker = np.indices((16, 16)).sum(axis=0) % 2 * 2.0 - 1
    with pytest.raises(km.DivergenceError, match="non-finite"):
        km.diffusion.step(checker, 1.0, 1.0, 0.01, scheme="ftcs", steps=400, check=False)


@pytest.mark.parametrize("scheme", ["ftcs", "implicit", "crank_nicolson"])
def test_neumann_conserves_heat(scheme):
    rng = np.random.default_rng(0)
    T0 = rng.random((40, 30))
    dt = 0.2 * 0.1**2 if scheme == "ftcs" else 0.05
    T = km.diffusion.step(T0, 1.0, dt, 0.1, scheme=scheme, steps=10)
    assert abs(T.sum() - T0.sum()) <= 1e-10 * T0.sum()
    assert T.max() <= T0.max() and T.min() >= T0.min()  # maximum principle for these steps


@pytest.mark.parametrize("scheme, order", [("implicit", 1), ("crank_nicolson", 2)])
def test_order_in_time(scheme, order):
    # A single discrete mode decays as exp(-kappa lam t) in exact time integration.
    shape, h, kappa, t_end = (32, 32), 1 / 32, 1.0, 0.02
    T0, lam = mode(shape, h, "neumann")
    errors, dts = [], []
    for steps in (4, 8, 16, 32):
        dt = t_end / steps
        T = km.diffusion.step(T0, kappa, dt, h, scheme=scheme, steps=steps, tol=1e-12)
        errors.append(np.abs(T - math.exp(-kappa * lam * t_end) * T0).max())
        dts.append(dt)
    p = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(p - order) < 0.2, f"{scheme}: observed order {p:.3f}, errors {errors}"


def test_gaussian_heat_kernel_2d():
    # A Gaussian of variance s0^2 in an (effectively) infinite plane stays Gaussian with variance
    # s0^2 + 2 kappa t and amplitude s0^2 / (s0^2 + 2 kappa t). Crank-Nicolson, O(h^2 + dt^2).
    n, L, kappa, s0, t_end, steps = 128, 4.0, 0.5, 0.2, 0.1, 20
    h = L / n
    X, Y = centres((n, n), h)
    r2 = (X - L / 2) ** 2 + (Y - L / 2) ** 2
    T0 = np.exp(-r2 / (2 * s0**2))
    T = km.diffusion.step(T0, kappa, t_end / steps, h, scheme="crank_nicolson", steps=steps)
    var = s0**2 + 2 * kappa * t_end
    exact = s0**2 / var * np.exp(-r2 / (2 * var))
    err = np.abs(T - exact).max()
    # Spatial error ~ h^2/12 * |lap^2 T| ~ 1e-3 here; time error smaller. Bound with a 3x margin.
    assert err < 3e-3, f"max error {err:.3e} against the heat kernel"


def test_solid_cells_insulate():
    shape = (20, 20)
    solid = np.zeros(shape, bool)
    solid[:, 10] = True  # a wall splitting the box in two
    T0 = np.zeros(shape)
    T0[:, :10] = 1.0
    T = km.diffusion.step(T0, 1.0, 0.5, 0.1, scheme="implicit", steps=10, solid=solid)
    assert np.abs(T[:, 11:]).max() < 1e-12 and np.allclose(T[:, :10], 1.0, atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(T=np.zeros(5)), "T:"),
        (dict(T=np.full((4, 4), np.nan)), "T: contains"),
        (dict(kappa=-1.0), "kappa:"),
        (dict(kappa=0.0), "kappa:"),
        (dict(dt=0.0), "dt:"),
        (dict(dt=float("inf")), "dt:"),
        (dict(h=0.0), "h:"),
        (dict(scheme="rk4"), "scheme:"),
        (dict(bc="robin"), "bc:"),
        (dict(steps=0), "steps:"),
        (dict(steps=2.5), "steps:"),
    ],
)
def test_bad_input(kwargs, match):
    args = dict(T=np.ones((4, 4)), kappa=1.0, dt=1e-3, h=0.1)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        km.diffusion.step(**args)


@pytest.mark.parametrize("scheme", ["ftcs", "implicit", "crank_nicolson"])
def test_stepper_matches_step_and_is_reusable(scheme):
    rng = np.random.default_rng(3)
    T0 = rng.random((24, 20))
    dt = 0.2 * 0.1**2 if scheme == "ftcs" else 0.01
    stepper = km.diffusion.Stepper(T0.shape, 1.0, dt, 0.1, scheme)
    once = stepper.step(T0, steps=6)
    twice = stepper.step(stepper.step(T0, steps=3), steps=3)
    direct = km.diffusion.step(T0, 1.0, dt, 0.1, scheme=scheme, steps=6)
    assert np.array_equal(once, direct)
    # Restarting from the intermediate field changes only the initial guesses of the solves.
    assert np.abs(once - twice).max() <= 1e-9
    with pytest.raises(ValueError, match="T: expected shape"):
        stepper.step(np.zeros((5, 5)))


@pytest.mark.parametrize("scheme, bound", [("crank_nicolson", 3e-3), ("ftcs", 3e-3), ("implicit", 3e-2)])
def test_gaussian_heat_kernel_3d(scheme, bound):
    # 3D: a Gaussian of variance s0^2 spreads to s0^2 + 2 kappa t with amplitude
    # (s0^2 / (s0^2 + 2 kappa t))^{3/2}. Errors measured: CN 2.0e-3, FTCS 1.5e-3 (space
    # O(h^2) dominates), backward Euler 1.7e-2 (O(dt) with 10 steps); heat is conserved.
    n, L, kappa, s0, t_end = 48, 3.0, 0.5, 0.25, 0.05
    h = L / n
    X = centres((n, n, n), h)
    r2 = sum((x - L / 2) ** 2 for x in X)
    T0 = np.exp(-r2 / (2 * s0**2))
    steps = 10 if scheme != "ftcs" else math.ceil(t_end / km.diffusion.stable_dt(h, kappa, 3))
    T = km.diffusion.step(T0, kappa, t_end / steps, h, scheme=scheme, steps=steps)
    var = s0**2 + 2 * kappa * t_end
    exact = (s0**2 / var) ** 1.5 * np.exp(-r2 / (2 * var))
    err = np.abs(T - exact).max()
    assert err < bound, f"{scheme}: max error {err:.3e}"
    assert abs(T.sum() / T0.sum() - 1) < 1e-10


@pytest.mark.parametrize("shape", [5, None, (4,), (0, 4)])
def test_stepper_shape_is_checked(shape):
    # Stepper took len(shape) before any check: a bare int raised TypeError.
    with pytest.raises(ValueError, match="^shape: "):
        km.diffusion.Stepper(shape, 1.0, 0.01, 0.1)
