"""km.poisson: accuracy against manufactured solutions, agreement of all methods, structure of
the operator, multigrid properties, and the handling of bad input."""

import math
import os
import signal
import threading
import time

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import kinema as km

METHODS = ["jacobi", "gauss_seidel", "cg", "multigrid", "mgpcg", "cholmod"]


def centres(shape, h):
    return np.meshgrid(*[(np.arange(n) + 0.5) * h for n in shape], indexing="ij")


def slope(hs, errors):
    return np.polyfit(np.log(hs), np.log(errors), 1)[0]


# ---------------------------------------------------------------- manufactured solutions

@pytest.mark.parametrize("d, sizes", [(2, [16, 32, 64, 128]), (3, [8, 16, 32])])
@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
def test_second_order(d, sizes, bc):
    # Dirichlet: u = prod sin(pi x_a) vanishes on the boundary of the unit cube. Neumann:
    # u = prod cos(pi x_a) has zero normal derivative and zero mean. Both: -lap u = d pi^2 u.
    mode = np.sin if bc == "dirichlet" else np.cos
    hs, errors = [], []
    for n in sizes:
        h = 1.0 / n
        exact = np.prod([mode(np.pi * x) for x in centres((n,) * d, h)], axis=0)
        u, info = km.poisson.solve(d * np.pi**2 * exact, h, bc, tol=1e-12)
        assert info.converged
        if bc == "neumann":
            assert abs(u.mean()) < 1e-12, f"gauge: mean(u) = {u.mean():.3e}, expected 0"
            exact = exact - exact.mean()
        hs.append(h)
        errors.append(np.abs(u - exact).max())
    p = slope(hs, errors)
    assert abs(p - 2) < 0.2, f"observed order {p:.3f} (errors {errors}), expected 2 +- 0.2"


def test_non_square_and_odd_grid_with_spacing():
    # A 2:1 box with odd cell counts: u = sin(pi x / Lx) sin(pi y / Ly), h = 0.02.
    h, shape = 0.02, (101, 51)
    X, Y = centres(shape, h)
    Lx, Ly = shape[0] * h, shape[1] * h
    exact = np.sin(np.pi * X / Lx) * np.sin(np.pi * Y / Ly)
    f = np.pi**2 * (1 / Lx**2 + 1 / Ly**2) * exact
    u, _ = km.poisson.solve(f, h, tol=1e-12)
    # Global error C h^2 with C ~ (pi/L)^2 / 12 * |u|_max-scale; 1e-3 leaves a 10x margin.
    err = np.abs(u - exact).max()
    assert err < 1e-3, f"max error {err:.3e} on a 101x51 grid, bound 1e-3"


# ---------------------------------------------------------------- all methods agree

def brute_force(f, h, bc, solid):
    """Reference by scipy's direct solver on the fluid cells (one cell pinned if singular)."""
    A = km.poisson.matrix(f.shape, h, bc, solid).tocsc()
    fluid = np.ones(f.size, bool) if solid is None else ~solid.ravel()
    b = f.ravel().copy()
    b[~fluid] = 0
    idx = np.flatnonzero(fluid)
    if bc == "neumann":
        b[idx] -= b[idx].mean()
        idx = idx[1:]  # one component here: pin its first cell
    x = np.zeros(f.size)
    x[idx] = spla.spsolve(A[idx][:, idx], b[idx])
    if bc == "neumann":
        x[fluid] -= x[fluid].mean()
    return x.reshape(f.shape)


def condition_estimate(shape, h):
    """lambda_max / lambda_min of the Dirichlet operator (an upper bound for the Neumann one's
    effective condition number on the range)."""
    lam_max = sum(4 / h**2 for _ in shape)
    lam_min = sum(4 / h**2 * math.sin(math.pi / (2 * n)) ** 2 for n in shape)
    return lam_max / lam_min


@pytest.mark.parametrize("shape", [(24, 20), (10, 12, 14)])
@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
@pytest.mark.parametrize("with_solid", [False, True])
def test_all_methods_agree(shape, bc, with_solid):
    rng = np.random.default_rng(7)
    h = 0.1
    f = rng.standard_normal(shape)
    solid = None
    if with_solid:
        solid = np.zeros(shape, bool)
        solid[tuple(slice(n // 3, n // 2) for n in shape)] = True  # a block, fluid stays connected
    ref = brute_force(f, h, bc, solid)
    tol = 1e-10
    bound = 3 * condition_estimate(shape, h) * tol * np.abs(ref).max()
    for method in METHODS:
        u, info = km.poisson.solve(f, h, bc, method, tol=tol, solid=solid, rhs_mean="remove")
        assert info.converged and info.residual <= tol, (method, info)
        err = np.abs(u - ref).max()
        assert err <= bound, f"{method}: max |u - u_ref| = {err:.3e} > {bound:.3e}"
        if solid is not None:
            assert np.all(u[solid] == 0), f"{method}: nonzero values in solid cells"


# ---------------------------------------------------------------- operator structure

@pytest.mark.parametrize("shape", [(7, 5), (4, 5, 3)])
def test_operator_symmetric_definite_and_eigenvalues(shape):
    h = 0.3
    A = km.poisson.matrix(shape, h, "dirichlet").toarray()
    assert np.array_equal(A, A.T)
    lam = np.linalg.eigvalsh(A)
    # Exact smallest eigenvalue of the cell-centred Dirichlet operator (sine modes).
    lam_min = sum(4 / h**2 * math.sin(math.pi / (2 * n)) ** 2 for n in shape)
    assert lam[0] > 0
    assert abs(lam[0] - lam_min) <= 1e-10 * lam_min, (lam[0], lam_min)

    N = km.poisson.matrix(shape, h, "neumann").toarray()
    assert np.array_equal(N, N.T)
    lamN = np.linalg.eigvalsh(N)
    scale = lamN[-1]
    assert abs(lamN[0]) < 1e-12 * scale, "Neumann: constants must be in the null space"
    assert lamN[1] > 1e-6 * scale, "Neumann: the null space must be one-dimensional"
    assert np.abs(N @ np.ones(N.shape[0])).max() < 1e-12 * scale


def test_solid_regions_add_null_space_and_block_flux():
    # An enclosed fluid pocket (solid ring) under Neumann: two components, two constants.
    shape = (12, 12)
    solid = np.zeros(shape, bool)
    solid[3:9, 3] = solid[3:9, 8] = solid[3, 3:9] = solid[8, 3:9] = True
    A = km.poisson.matrix(shape, 1.0, "neumann", solid)
    fluid = ~solid.ravel()
    lam = np.linalg.eigvalsh(A.toarray()[np.ix_(fluid, fluid)])
    assert np.sum(np.abs(lam) < 1e-12 * lam[-1]) == 2
    # Under Dirichlet the pocket (no boundary face) is the only singular component.
    D = km.poisson.matrix(shape, 1.0, "dirichlet", solid)
    lamD = np.linalg.eigvalsh(D.toarray()[np.ix_(fluid, fluid)])
    assert np.sum(np.abs(lamD) < 1e-12 * lamD[-1]) == 1
    # Solve with data compatible per component: each component keeps zero mean.
    rng = np.random.default_rng(1)
    f = rng.standard_normal(shape)
    f[solid] = 0
    inner = np.zeros(shape, bool)
    inner[4:8, 4:8] = True
    outer = ~solid & ~inner
    f[inner] -= f[inner].mean()
    f[outer] -= f[outer].mean()
    for method in ["mgpcg", "cg", "cholmod"]:
        u, info = km.poisson.solve(f, 1.0, "neumann", method, solid=solid, tol=1e-11)
        assert abs(u[inner].mean()) < 1e-12 and abs(u[outer].mean()) < 1e-12, method
        r = f - km.poisson.laplacian(u, 1.0, "neumann", solid)
        assert np.abs(r[~solid]).max() < 1e-9 * np.abs(f).max(), method


@pytest.mark.parametrize("shape", [(9, 13), (5, 6, 7)])
@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
def test_matrix_free_equals_assembled(shape, bc):
    rng = np.random.default_rng(2)
    solid = rng.random(shape) < 0.15
    u = rng.standard_normal(shape)
    A = km.poisson.matrix(shape, 0.5, bc, solid)
    Au = km.poisson.laplacian(u, 0.5, bc, solid)
    assert np.abs(A @ u.ravel() - Au.ravel()).max() < 1e-13 * np.abs(Au).max()
    assert np.all(Au[solid] == 0)


# ---------------------------------------------------------------- multigrid

@pytest.mark.parametrize("shape", [(37, 29), (64, 64), (19, 22, 17), (32, 32, 32)])
@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
@pytest.mark.parametrize("with_solid", [False, True])
def test_vcycle_is_symmetric_positive(shape, bc, with_solid):
    # MGPCG needs a symmetric positive definite preconditioner: <V a, b> = <a, V b>.
    rng = np.random.default_rng(3)
    solid = rng.random(shape) < 0.1 if with_solid else None
    s = km.poisson.Solver(shape, 0.1, bc, method="mgpcg", solid=solid)
    a, b = rng.standard_normal(shape), rng.standard_normal(shape)
    for v in (a, b):
        s._core.project(v)
    Va, Vb = s.vcycle(a), s.vcycle(b)
    lhs, rhs = np.sum(Va * b), np.sum(a * Vb)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs), (lhs, rhs)
    assert np.sum(Va * a) > 0


@pytest.mark.parametrize("shape", [(29, 24), (26, 31), (11, 9, 12), (10, 12, 9)])
@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
def test_restriction_is_scaled_transpose_of_prolongation(shape, bc):
    # R = P^T / 2^d entry by entry, on odd and even sizes with random solids (brute force:
    # one unit vector at a time).
    rng = np.random.default_rng(11)
    solid = rng.random(shape) < 0.15
    s = km.poisson.Solver(shape, 0.1, bc, method="mgpcg", solid=solid)
    assert s.levels >= 2
    cshape = s._core.transfer(0, np.zeros(shape), True).shape
    nf, nc = solid.size, int(np.prod(cshape))
    P = np.stack([s._core.transfer(0, np.eye(1, nc, c).reshape(cshape), False).ravel()
                  for c in range(nc)], axis=1)
    R = np.stack([s._core.transfer(0, np.eye(1, nf, f).reshape(shape), True).ravel()
                  for f in range(nf)], axis=1)
    fluid = ~solid.ravel()
    diff = np.abs(R[:, fluid] * 2 ** len(shape) - P[fluid].T).max()
    assert diff < 1e-15, f"max |2^d R - P^T| = {diff:.3e}"
    # P reproduces constants away from Dirichlet boundaries and solids.
    assert np.all(P.sum(axis=1)[fluid] <= 1 + 1e-15)


def mgpcg_iterations(shape, tol):
    rng = np.random.default_rng(4)
    f = rng.standard_normal(shape)
    _, info = km.poisson.solve(f, 1.0 / shape[0], tol=tol)
    return info.iterations


def test_mgpcg_iterations_flat_2d():
    its = [mgpcg_iterations((n, n), 1e-8) for n in (64, 128, 256, 512)]
    assert max(its) - min(its) <= 2 and max(its) <= 12, f"MGPCG iterations {its}"


def test_mgpcg_iterations_flat_3d():
    its = [mgpcg_iterations((n, n, n), 1e-8) for n in (16, 32, 64)]
    assert max(its) - min(its) <= 2 and max(its) <= 12, f"MGPCG iterations {its}"


@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
def test_mgpcg_iterations_flat_with_obstacle(bc):
    # Coarse levels keep a cell fluid when any child is; the solid disk/ball must not make the
    # iteration count grow with the grid.
    rng = np.random.default_rng(4)
    its = []
    for shape in [(64, 64), (256, 256), (32, 32, 32), (64, 64, 64)]:
        h = 1.0 / shape[0]
        X = centres(shape, h)
        solid = sum((x - 0.4) ** 2 for x in X) < 0.2**2
        f = rng.standard_normal(shape)
        _, info = km.poisson.solve(f, h, bc, tol=1e-8, solid=solid, rhs_mean="remove")
        its.append(info.iterations)
    assert max(its) - min(its) <= 2 and max(its) <= 12, f"MGPCG iterations with an obstacle {its}"


@pytest.mark.slow
def test_mgpcg_iterations_flat_large():
    its2 = [mgpcg_iterations((n, n), 1e-8) for n in (64, 256, 1024, 2048)]
    its3 = [mgpcg_iterations((n, n, n), 1e-8) for n in (32, 64, 128, 256)]
    assert max(its2) - min(its2) <= 2, f"2D MGPCG iterations {its2}"
    assert max(its3) - min(its3) <= 2, f"3D MGPCG iterations {its3}"


def test_multigrid_converges_with_solids():
    rng = np.random.default_rng(5)
    shape = (96, 80)
    solid = np.zeros(shape, bool)
    X, Y = centres(shape, 1.0 / 96)
    solid[(X - 0.4) ** 2 + (Y - 0.4) ** 2 < 0.15**2] = True
    f = rng.standard_normal(shape)
    for method in ("multigrid", "mgpcg"):
        u, info = km.poisson.solve(f, 1 / 96, "neumann", method, solid=solid, rhs_mean="remove")
        assert info.converged and info.iterations < 40, (method, info.iterations)


# ---------------------------------------------------------------- behaviour

def test_neumann_incompatible_rhs_is_rejected():
    f = np.ones((16, 16))
    with pytest.raises(ValueError, match="f: incompatible"):
        km.poisson.solve(f, 0.1, "neumann")
    u, info = km.poisson.solve(f, 0.1, "neumann", rhs_mean="remove")
    assert info.converged and np.abs(u).max() < 1e-12


def test_zero_rhs_gives_zero():
    u, info = km.poisson.solve(np.zeros((8, 8, 8)), 0.1)
    assert info.converged and not u.any()


def test_initial_guess_is_used():
    rng = np.random.default_rng(6)
    f = rng.standard_normal((64, 64))
    u, info = km.poisson.solve(f, 1 / 64, method="cg")
    u2, info2 = km.poisson.solve(f, 1 / 64, method="cg", x0=u)
    assert info2.iterations <= 1 < info.iterations


def test_convergence_error_when_max_iter_too_small():
    f = np.random.default_rng(0).standard_normal((64, 64))
    with pytest.raises(km.ConvergenceError, match="residual") as exc:
        km.poisson.solve(f, 1 / 64, method="jacobi", max_iter=5)
    assert exc.value.info.iterations == 5 and not exc.value.info.converged
    _, info = km.poisson.solve(f, 1 / 64, method="jacobi", max_iter=5, raise_on_failure=False)
    assert not info.converged and len(info.history) == 6


@pytest.mark.parametrize("threads", [1, 2])
def test_bitwise_reproducible(threads):
    f = np.random.default_rng(8).standard_normal((48, 40, 36))
    saved = km.get_num_threads()
    try:
        km.set_num_threads(2)
        ref, _ = km.poisson.solve(f, 0.1)
        km.set_num_threads(threads)
        again, _ = km.poisson.solve(f, 0.1)
    finally:
        km.set_num_threads(saved)
    assert np.array_equal(ref, again)


def test_ctrl_c_interrupts_a_long_solve(ctrl_c_delay):
    f = np.random.default_rng(9).standard_normal((512, 512))
    delay = ctrl_c_delay(lambda: km.poisson.solve(f, 1.0, method="jacobi", tol=1e-14), after=0.3)
    assert delay < 1.7, f"took {delay:.2f} s to honour Ctrl-C"


# ---------------------------------------------------------------- bad input

@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(f=np.zeros(10)), "f:"),
        (dict(f=np.zeros((2, 2, 2, 2))), "f:"),
        (dict(f=np.full((4, 4), np.nan)), "f: contains"),
        (dict(f=[[1, "a"], [2, 3]]), "f:"),
        (dict(h=0.0), "h:"),
        (dict(h=-1.0), "h:"),
        (dict(h=float("nan")), "h:"),
        (dict(bc="robin"), "bc:"),
        (dict(method="sor"), "method:"),
        (dict(tol=0.0), "tol:"),
        (dict(tol=float("inf")), "tol:"),
        (dict(max_iter=0), "max_iter:"),
        (dict(x0=np.zeros((3, 3))), "x0:"),
        (dict(x0=np.full((4, 4), np.inf)), "x0:"),
        (dict(solid=np.zeros((3, 4), bool)), "solid:"),
        (dict(solid=np.full((4, 4), 0.5)), "solid:"),
    ],
)
def test_bad_input_raises_value_error(kwargs, match):
    args = dict(f=np.ones((4, 4)), h=0.1)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        km.poisson.solve(**args)


def test_absurd_sizes_are_rejected():
    with pytest.raises(ValueError, match="shape:"):
        km.poisson.matrix((100000, 100000, 100000), 0.1)
    with pytest.raises(ValueError, match="shape:"):
        km.poisson.matrix((0, 4), 0.1)
    with pytest.raises(ValueError, match="shape:"):
        km.poisson.Solver((4,), 0.1)


# ---------------------------------------------------------------- periodic boundaries

def test_periodic_second_order():
    # u = prod sin(2 pi x_a + a) on the unit torus: -lap u = d (2 pi)^2 u, zero mean.
    for d, sizes in ((2, [16, 32, 64, 128]), (3, [8, 16, 32])):
        hs, errors = [], []
        for n in sizes:
            h = 1.0 / n
            exact = np.prod([np.sin(2 * np.pi * x + a) for a, x in enumerate(centres((n,) * d, h))], axis=0)
            exact -= exact.mean()
            u, info = km.poisson.solve(d * (2 * np.pi) ** 2 * exact, h, "periodic", tol=1e-12)
            assert info.converged
            assert abs(u.mean()) < 1e-12, f"gauge: mean(u) = {u.mean():.3e}, expected 0"
            hs.append(h)
            errors.append(np.abs(u - exact).max())
        p = slope(hs, errors)
        assert abs(p - 2) < 0.2, f"{d}D periodic: observed order {p:.3f} (errors {errors}), expected 2 +- 0.2"


@pytest.mark.parametrize("shape", [(32, 24), (16, 12, 8)])
def test_periodic_methods_agree_with_solids(shape):
    # MGPCG, multigrid and CG reach the same solution; the operator wraps (checked against
    # numpy.roll with zero flux into solid cells).
    rng = np.random.default_rng(21)
    solid = rng.random(shape) < 0.1
    f = rng.standard_normal(shape)
    f[solid] = 0
    f[~solid] -= f[~solid].mean()
    sols = {}
    for method in ("cg", "multigrid", "mgpcg", "cholmod"):
        u, info = km.poisson.solve(f, 0.5, "periodic", method=method, tol=1e-11, solid=solid)
        assert info.converged, method
        sols[method] = u
        r = f - km.poisson.laplacian(u, 0.5, "periodic", solid)
        assert np.abs(r[~solid]).max() < 1e-8 * np.abs(f).max(), (method, np.abs(r).max())
    for method in ("multigrid", "mgpcg", "cholmod"):
        diff = np.abs(sols[method] - sols["cg"]).max()
        assert diff < 1e-8 * np.abs(sols["cg"]).max(), f"{method} vs cg: {diff:.3e}"
    u = rng.standard_normal(shape)
    u[solid] = 0
    fluid = (~solid).astype(float)
    lap = np.zeros(shape)
    for a in range(len(shape)):
        for s in (1, -1):
            nb = np.roll(u, s, axis=a)
            coupled = fluid * np.roll(fluid, s, axis=a)
            lap += coupled * (u - nb) / 0.25
    assert np.abs(km.poisson.laplacian(u, 0.5, "periodic", solid) - lap).max() < 1e-12 * np.abs(lap).max()
    A = km.poisson.matrix(shape, 0.5, "periodic", solid)
    assert np.abs(A @ u.ravel() - lap.ravel()).max() < 1e-12 * np.abs(lap).max()


@pytest.mark.parametrize("shape", [(32, 24), (16, 12, 8)])
def test_periodic_vcycle_symmetric_and_transfers_transposed(shape):
    rng = np.random.default_rng(22)
    solid = rng.random(shape) < 0.1
    s = km.poisson.Solver(shape, 0.1, "periodic", method="mgpcg", solid=solid)
    assert s.levels >= 2
    a, b = rng.standard_normal(shape), rng.standard_normal(shape)
    for v in (a, b):
        s._core.project(v)
    Va, Vb = s.vcycle(a), s.vcycle(b)
    assert abs(np.sum(Va * b) - np.sum(a * Vb)) <= 1e-12 * abs(np.sum(Va * b))
    assert np.sum(Va * a) > 0
    cshape = s._core.transfer(0, np.zeros(shape), True).shape
    nf, nc = solid.size, int(np.prod(cshape))
    P = np.stack([s._core.transfer(0, np.eye(1, nc, c).reshape(cshape), False).ravel() for c in range(nc)], axis=1)
    R = np.stack([s._core.transfer(0, np.eye(1, nf, f).reshape(shape), True).ravel() for f in range(nf)], axis=1)
    fluid = ~solid.ravel()
    diff = np.abs(R[:, fluid] * 2 ** len(shape) - P[fluid].T).max()
    assert diff < 1e-15, f"max |2^d R - P^T| = {diff:.3e}"
    # periodic: no boundary loses mass, so P reproduces constants on every fluid cell whose
    # coarse neighbourhood is fluid; with no solids, exactly everywhere
    s0 = km.poisson.Solver(shape, 0.1, "periodic", method="mgpcg")
    ones = s0._core.transfer(0, np.ones(cshape), False)
    assert np.abs(ones - 1).max() < 1e-15


def test_periodic_mgpcg_iterations_flat():
    # The periodic problem has the constant null space like pure Neumann; MGPCG's iteration
    # count must not grow with the grid (McAdams et al. 2010 report flat counts for Neumann).
    rng = np.random.default_rng(23)
    its = {}
    for shape in [(64, 64), (128, 128), (256, 256), (512, 512), (16, 16, 16), (32, 32, 32), (64, 64, 64)]:
        f = rng.standard_normal(shape)
        _, info = km.poisson.solve(f, 1.0 / shape[0], "periodic", tol=1e-8, rhs_mean="remove")
        its[shape] = info.iterations
    two = [v for k, v in its.items() if len(k) == 2]
    three = [v for k, v in its.items() if len(k) == 3]
    for group in (two, three):
        assert max(group) - min(group) <= 2 and max(group) <= 12, f"periodic MGPCG iterations {its}"
    cg_its = [km.poisson.solve(rng.standard_normal((n, n)), 1.0 / n, "periodic", method="cg", tol=1e-8,
                               rhs_mean="remove")[1].iterations for n in (64, 128)]
    assert cg_its[1] > 1.5 * cg_its[0], f"CG iterations {cg_its} should grow ~2x per refinement"


def test_periodic_red_black_needs_even_sizes():
    f = np.random.default_rng(24).standard_normal((15, 16))
    f -= f.mean()
    with pytest.raises(ValueError, match="shape: .*even"):
        km.poisson.solve(f, 0.1, "periodic", method="mgpcg")
    u, info = km.poisson.solve(f, 0.1, "periodic", method="cg", tol=1e-10)
    assert info.converged
    r = f - km.poisson.laplacian(u, 0.1, "periodic")
    assert np.abs(r).max() < 1e-8 * np.abs(f).max()


@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
def test_non_cubic_3d_box_with_spacing_and_single_precision_input(bc):
    # A 6:4:10 box of side lengths L_a, h = 0.3 / r: u = prod sin(pi x_a / L_a) (Dirichlet) or
    # prod cos (Neumann), -lap u = pi^2 sum 1/L_a^2 u. Second order; the r = 2 right-hand side
    # is given as Fortran-ordered float32 (converted on entry, its rounding 6e-8 << h^2 error).
    # Every method agrees with the direct solve on the coarse grid.
    errors, hs = [], []
    for r in (1, 2, 4):
        shape, h = (6 * r, 4 * r, 10 * r), 0.3 / r
        X = centres(shape, h)
        lengths = [n * h for n in shape]
        mode = np.sin if bc == "dirichlet" else np.cos
        exact = np.prod([mode(np.pi * x / L) for x, L in zip(X, lengths)], axis=0)
        f = np.pi**2 * sum(1 / L**2 for L in lengths) * exact
        if r == 2:
            f = np.asfortranarray(f.astype(np.float32))
        if bc == "neumann":
            exact = exact - exact.mean()
        u, info = km.poisson.solve(f, h, bc, tol=1e-10)
        assert info.converged
        if r == 1:
            for method in ("multigrid", "cg", "cholmod"):
                other, _ = km.poisson.solve(f, h, bc, method=method, tol=1e-10)
                assert np.abs(other - u).max() < 1e-8, method
        errors.append(np.abs(u - exact).max())
        hs.append(h)
    p = slope(hs, errors)
    assert abs(p - 2) < 0.15, f"observed order {p:.3f} (errors {errors})"


@pytest.mark.parametrize("shape", [(16, 12), (8, 6, 7)])
@pytest.mark.parametrize("c", [1e-310, 1e-200, 1e200, 1e300])
def test_tiny_and_huge_right_hand_sides_are_solved_by_linearity(shape, c):
    # -lap u = c f has the solution c u: the norms (sums of squares) used to underflow for
    # c = 1e-200 and below (u = 0 returned as converged with residual 0) and overflow for
    # c = 1e200 and above (a representable solution refused as "overflows float64").
    f = np.random.default_rng(5).standard_normal(shape)
    for method in km.poisson.METHODS:
        if method == "jacobi":
            continue  # slow to 1e-8 on these grids, and it shares the loop with multigrid
        u1, _ = km.poisson.solve(f, 0.1, method=method, tol=1e-10)
        with np.errstate(under="ignore"):
            uc, info = km.poisson.solve(c * f, 0.1, method=method, tol=1e-10)
            assert info.converged and info.residual <= 1e-10
            # tol 1e-10 on both solves; subnormal c f keeps ~16 - 14 = 2 fewer digits
            err = np.abs(uc / c - u1).max() / np.abs(u1).max()
        assert err < (1e-6 if c < 1e-300 else 1e-8), (method, err)
