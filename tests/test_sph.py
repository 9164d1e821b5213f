"""km.sph: neighbour search against brute force, the kernel, scene helpers, hydrostatic tank,
dam break against Martin and Moyce (1952), stability under abuse, zero-copy state and bad input."""

import warnings

import numpy as np
import pytest

import kinema as km

G = 9.81


def down(d):
    """Gravity along -y in d dimensions [m/s^2]."""
    return (0, -G, 0)[:d]


def brute_pairs(x, r):
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    i, j = np.nonzero(np.triu(d2 < r * r, k=1))
    return np.stack([i, j], axis=1).astype(np.int64)


# ---------------------------------------------------------------- neighbour search

@pytest.mark.parametrize("d", [2, 3])
def test_neighbor_pairs_match_brute_force_random(d):
    rng = np.random.default_rng(4 + d)
    x = rng.uniform(-1.0, 2.0, size=(700, d))
    for r in (0.05, 0.2, 0.7, 5.0):
        got = km.sph.neighbor_pairs(x, r)
        want = brute_pairs(x, r)
        assert got.dtype == np.int64 and got.shape[1] == 2
        np.testing.assert_array_equal(got, want, err_msg=f"d={d}, radius={r}")


@pytest.mark.parametrize("d", [2, 3])
def test_neighbor_pairs_clustered_and_duplicates(d):
    rng = np.random.default_rng(11)
    centres = rng.uniform(0, 10, size=(5, d))
    clustered = np.concatenate([c + 1e-3 * rng.standard_normal((80, d)) for c in centres])
    duplicates = np.repeat(rng.uniform(0, 1, size=(20, d)), 4, axis=0)
    far = np.array([[1e6] * d, [-1e6] * d])  # stretches the bounding box: coarse-cell fallback
    for x in (clustered, duplicates, np.concatenate([clustered, far])):
        np.testing.assert_array_equal(km.sph.neighbor_pairs(x, 0.01), brute_pairs(x, 0.01))


def test_neighbor_pairs_strict_radius_and_trivial_inputs():
    # Integer lattice: distances are exact, so |x_i - x_j| == radius must be excluded.
    x = km.sph.block([0, 0], [4, 4], 1.0)
    got = km.sph.neighbor_pairs(x, 1.0)
    assert len(got) == 0
    assert len(km.sph.neighbor_pairs(x, 1.0 + 1e-12)) == 2 * 4 * 3
    assert km.sph.neighbor_pairs(np.zeros((0, 3)), 1.0).shape == (0, 2)
    assert km.sph.neighbor_pairs(np.zeros((1, 2)), 1.0).shape == (0, 2)


def brute_boundary_pairs(x, xb, r):
    d2 = ((x[:, None, :] - xb[None, :, :]) ** 2).sum(-1)
    i, b = np.nonzero(d2 < r * r)
    return np.stack([i, b], axis=1).astype(np.int64)


def sorted_rows(p):
    return p[np.lexsort((p[:, 1], p[:, 0]))]


@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_neighbor_lists_in_use_equal_brute_force_every_step(method):
    # The Verlet lists are searched again only when a particle has moved half the skin, and
    # filtered to the support radius each step: the pairs a step uses must be exactly those a
    # fresh brute-force search finds, at every step of a collapsing column (fluid-fluid and
    # fluid-boundary, the obstacle and the domain walls included).
    s = 0.01
    lower, upper = [0, 0], [0.3, 0.25]
    x = km.sph.block([0, 0], [0.1, 0.2], s)
    obstacle = km.sph.block([0.15, 0], [0.17, 0.04], s)
    fluid = km.sph.Fluid(x, s, gravity=down(2), method=method, domain=(lower, upper), boundary=obstacle,
                         reorder_every=3)
    xb = np.concatenate([obstacle, km.sph.box_boundary(lower, upper, s, layers=2)])
    h = fluid.support_radius
    fluid.advance(0.08)  # the column is collapsing: particles move up to ~1 m/s
    assert np.abs(fluid.v).max() > 0.5
    rebuilds = 0
    steps = 60 if method == "wcsph" else 25
    for k in range(steps):
        pairs, bpairs = fluid.neighbor_pairs()
        np.testing.assert_array_equal(sorted_rows(pairs), brute_pairs(fluid.x, h), err_msg=f"step {k}")
        np.testing.assert_array_equal(sorted_rows(bpairs), brute_boundary_pairs(fluid.x, xb, h),
                                      err_msg=f"boundary pairs, step {k}")
        rebuilds += fluid.step(fluid.stable_dt()).neighbor_rebuild
    if method == "wcsph":  # small steps: the lists must outlive several of them
        assert rebuilds < steps / 3, f"{rebuilds} rebuilds in {steps} steps"


# ---------------------------------------------------------------- kernel

@pytest.mark.parametrize("d", [2, 3])
def test_kernel_normalised_and_compact(d):
    h = 0.37
    r = np.linspace(0, h, 200001)
    w = km.sph.kernel(r, h, d)
    shell = 2 * np.pi * r if d == 2 else 4 * np.pi * r**2
    integral = np.trapezoid(shell * w, r) if hasattr(np, "trapezoid") else np.trapz(shell * w, r)
    assert abs(integral - 1) < 1e-8, f"integral of W over R^{d} = {integral!r}, expected 1"
    sigma = 40 / (7 * np.pi * h**2) if d == 2 else 8 / (np.pi * h**3)
    assert km.sph.kernel(0.0, h, d) == pytest.approx(sigma, rel=1e-15)
    assert km.sph.kernel(h, h, d) == 0 and km.sph.kernel(2 * h, h, d, derivative=1) == 0


@pytest.mark.parametrize("d", [2, 3])
def test_kernel_derivatives_match_finite_differences(d):
    h = 1.3
    r = np.linspace(0.01, 0.99, 97) * h
    eps = 1e-6
    for k in (1, 2):
        fd = (km.sph.kernel(r + eps, h, d, k - 1) - km.sph.kernel(r - eps, h, d, k - 1)) / (2 * eps)
        an = km.sph.kernel(r, h, d, k)
        # Central differences: error ~ eps^2 W''' away from the kink at q = 1/2.
        assert np.abs(fd - an).max() < 1e-5 * np.abs(an).max(), f"derivative {k}, d={d}"
    # The first derivative is continuous at q = 1/2 and q = 1.
    assert km.sph.kernel(0.5 * h - 1e-12, h, d, 1) == pytest.approx(km.sph.kernel(0.5 * h + 1e-12, h, d, 1))


def test_lattice_density_is_rest_density():
    # A filled lattice samples the kernel's partition of unity: interior density ~ rho0.
    for d in (2, 3):
        s = 0.01
        x = km.sph.block([0] * d, [0.2] * d, s)
        fluid = km.sph.Fluid(x, s, gravity=[0] * d, domain=([0] * d, [0.2] * d))
        err = fluid.density_error()
        assert err < 1e-3, f"{d}D: lattice with walls compressed by {err:.2e} on average"
        assert np.abs(fluid.density / 1000 - 1).max() < 2e-3


# ---------------------------------------------------------------- helpers

def test_block_and_box_boundary():
    x = km.sph.block([0, 0, 0], [1, 0.5, 0.25], 0.05)
    assert x.shape == (20 * 10 * 5, 3)
    np.testing.assert_allclose(x.min(0), [0.025] * 3)
    b = km.sph.box_boundary([0, 0], [1, 0.5], 0.05, layers=2)
    inside = np.all((b > 0) & (b < [1, 0.5]), axis=1)
    assert not inside.any()
    assert len(b) == 24 * 14 - 20 * 10
    assert b.min(0) == pytest.approx([-0.075, -0.075])


def test_akinci_volumes_of_a_single_layer_wall():
    # psi_b = rho0 / sum_k W_bk: a denser wall gets proportionally smaller volumes.
    s = 0.02
    x = km.sph.block([0, 0.1], [0.4, 0.3], s)
    coarse = np.stack([np.arange(-0.1, 0.5, s), np.zeros(30)], axis=1)
    fine = np.stack([np.arange(-0.1, 0.5, s / 2), np.zeros(60)], axis=1)
    psi_c = km.sph.Fluid(x, s, boundary=coarse).boundary_psi
    psi_f = km.sph.Fluid(x, s, boundary=fine).boundary_psi
    assert psi_c[15] / psi_f[30] == pytest.approx(2.0, rel=0.02)


# ---------------------------------------------------------------- hydrostatic tank

@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_hydrostatic_tank(method):
    s, H, L = 0.01, 0.2, 0.3
    x = km.sph.block([0, 0], [L, H], s)
    # Viscous for both methods (issue 15: DFSPH ran inviscid here because with nu = 0.01 its
    # column kept moving and its pressure rose to 1.75 rho g; the viscous step bound then sat
    # past forward Euler's limit for settled particles and DFSPH's warm start could not give
    # pressure back). nu = 0.01 caps DFSPH's dt at 0.05 s^2 / nu = 0.5 ms.
    fluid = km.sph.Fluid(x, s, gravity=down(2), method=method, domain=([0, 0], [L, 0.4]), viscosity=0.01)
    fluid.advance(1.0)
    err = fluid.density_error()
    # WCSPH's column rings acoustically (period 4H/c ~ 0.04 s, amplitude rho c v ~ 10% of
    # rho g H): average the pressure over a few periods, binned by height.
    ys, ps = [], []
    for _ in range(25):
        fluid.advance(0.004)
        ys.append(fluid.x[:, 1].copy())
        ps.append(fluid.pressure.copy())
    y, p = np.concatenate(ys), np.concatenate(ps)
    top = fluid.x[:, 1].max() + s / 2
    # Volume loss: the free surface may not sink by more than a quarter spacing.
    assert top > H - 0.25 * s, f"{method}: surface at {top:.4f} m, started at {H} m"
    bound = 0.01 if method == "wcsph" else 2e-3
    assert err < bound, f"{method}: mean compression {err:.2e}, bound {bound}"
    assert fluid.kinetic_energy() < 1e-2 * 1000 * L * H * G * H
    # Pressure against rho g (H - y) away from the surface and bottom rows (DFSPH: p_i =
    # rho_i^2 (k_i + k^v_i) of both its solves, the pressure whose force they applied). 10% on
    # the slope: the SPH pressure gradient of the settled (no longer lattice) arrangement is
    # normalised only to a few percent (measured: WCSPH 7.6%, DFSPH 6.4%); the p = 0 level
    # within the 3 spacings of the kernel support's surface deficiency.
    mask = (y > 3 * s) & (y < top - 5 * s)
    slope, intercept = np.polyfit(y[mask], p[mask], 1)
    assert slope == pytest.approx(-1000 * G, rel=0.1), f"{method}: dp/dy = {slope:.0f}, expected {-1000 * G:.0f}"
    assert -intercept / slope == pytest.approx(top, abs=3 * s), f"{method}: p = 0 at {-intercept / slope:.3f}"


# The viscous column at rest of issue 15, both methods in 2D and 3D: a column of depth H (25 and
# 20 particle rows) in a closed tank, settled for SETTLE s by zeroing the velocities every 0.02 s
# (the lattice rearranges), then FREE s on its own with nu = 0.01 at the steps advance() takes.
REST = {2: dict(s=0.02, size=[1.0, 0.5]), 3: dict(s=0.025, size=[0.3, 0.5, 0.15])}
SETTLE, FREE = 0.5, 0.5


def column_at_rest(method, d, tol=1e-3, **options):
    s, size = REST[d]["s"], REST[d]["size"]
    H = size[1]
    box = list(size)
    box[1] = 2 * H
    fluid = km.sph.Fluid(km.sph.block([0] * d, size, s), s, gravity=down(d), method=method, domain=([0] * d, box),
                         viscosity=0.01, tol=tol, **options)
    with warnings.catch_warnings():
        # The settling builds the pressure of a lattice released without any: at tol 1e-4 a
        # few of its steps stop at max_iter (advance warns); the free steps are checked.
        warnings.simplefilter("ignore", RuntimeWarning)
        while fluid.time < SETTLE - 1e-9:
            fluid.advance(0.02)
            fluid.v[:] = 0
    iterations, energies, ys, ps = [], [], [], []
    unconverged = 0
    end = fluid.time + FREE
    while fluid.time < end - 1e-12:
        st = fluid.step(min(fluid.stable_dt(), end - fluid.time))
        iterations.append(st.iterations)
        unconverged += not (st.density_converged and st.divergence_converged)
        energies.append(fluid.kinetic_energy())
        if fluid.time > end - 0.1:  # the last 0.1 s: 2.5 periods of WCSPH's acoustic ringing
            ys.append(fluid.x[:, 1].copy())
            ps.append(fluid.pressure.copy())
    mass = fluid.mass * fluid.n
    v_rms = np.sqrt(2 * max(energies[len(energies) // 2:]) / mass)
    top = np.percentile(fluid.x[:, 1], 99.5) + s / 2
    y, p = np.concatenate(ys), np.concatenate(ps)
    mask = (y > 2 * s) & (y < top - 3 * s)
    slope, intercept = np.polyfit(y[mask], p[mask], 1)
    return dict(H=H, s=s, v_rms=v_rms, slope=slope / (-1000 * G), p0=-intercept / slope, top=top,
                iterations=np.array(iterations), unconverged=unconverged)


# Bounds. Velocity: the rms speed of the free second half, at most 2% of sqrt(2 g H) (the speed
# of a particle falling the column's height, 0.063 m/s at H = 0.5 m). WCSPH measured 0.024-0.027
# (2D) and 0.048 (3D) m/s: what is left of the settling. Issue 15's DFSPH had 0.09 m/s rms (2 J)
# with peaks of 1 m/s. Pressure: the least-squares slope of p against y over the last 0.1 s,
# within 10% of rho0 g (the settled arrangement's SPH gradient is normalised to a few percent;
# measured 2D: WCSPH 1.02-1.03, DFSPH 1.02-1.05), and p = 0 within 3 spacings of the surface.
# DFSPH iterations (constant-density solve) per step: mean at most 10 and none above 60 at
# tol = 1e-3 (the issue saw 50-100 per step). DFSPH's walls hold what the fluid pushes, as
# WCSPH's do (with Akinci's single term a 3D column read a slope of 1.22-1.29 rho0 g, its bottom
# row 2.1 rho0 g (H - y)), and
# its density solve under-relaxes the compressed particles' increments (0.8): at the paper's
# full increment the warm-started Jacobi overshot every step and the column bounced as a whole (2D 0.063-0.09 m/s under the plain mean rule, 3D 0.070-0.084 m/s, mean
# vertical speed +-0.028 m/s); measured after: 2D 0.026 m/s, slope 1.03, 7.7 iterations (peak
# 11); 3D 0.046 m/s, slope 1.08 (1.02 before), 9.1 (peak 19) (these with walls="mirror").
# DFSPH's default walls (one stiffness per wall sample, the filled tank's conservative walls)
# hold the same bounds, the 3D column only just: measured 2D 0.021 m/s, slope 1.03; 3D 0.062
# m/s, slope 1.03, 8.0 iterations (peak 42): the 3D column sags and bounces as a whole (mean
# vertical speed +-0.04 m/s, bench/sph/sph_column_cycle.py --d 3 --series), and
# an earlier build of the same sums in another order read 0.051. At tol 2e-3 and 5e-3 (coarse
# correction on) it reads 0.023 m/s.
REST_CASES = [
    pytest.param("wcsph", 2, None, id="wcsph-2d"),
    pytest.param("dfsph", 2, None, id="dfsph-2d"),
    pytest.param("wcsph", 3, None, id="wcsph-3d"),
    pytest.param("dfsph", 3, None, id="dfsph-3d"),
    pytest.param("dfsph", 2, "mirror", id="dfsph-mirror-2d"),
    pytest.param("dfsph", 3, "mirror", id="dfsph-mirror-3d"),
]


@pytest.mark.parametrize("method, d, walls", REST_CASES)
def test_viscous_column_at_rest(method, d, walls):
    r = column_at_rest(method, d, walls=walls)
    H, s = r["H"], r["s"]
    assert r["v_rms"] < 0.02 * np.sqrt(2 * G * H), f"{method} {d}D: rms speed {r['v_rms']:.3f} m/s"
    assert r["slope"] == pytest.approx(1, abs=0.1), f"{method} {d}D: dp/dy = {r['slope']:.3f} rho0 g"
    assert r["p0"] == pytest.approx(r["top"], abs=3 * s), f"{method} {d}D: p = 0 at {r['p0']:.3f} m"
    if method == "dfsph":
        its = r["iterations"]
        assert its.mean() <= 10 and its.max() <= 60, f"{d}D: iterations per step mean {its.mean():.1f}, max {its.max()}"
        assert r["unconverged"] == 0, f"{d}D: {r['unconverged']} free steps stopped at max_iter"


@pytest.mark.parametrize("tol", [pytest.param(1e-4, marks=pytest.mark.slow), 3e-4])
@pytest.mark.parametrize("d", [2, 3])
def test_dfsph_column_at_rest_tight_tol(d, tol):
    # At tol = 1e-4 and 3e-4 DFSPH's column holds in both dimensions, with the pressure of the
    # bounds above, every solve within its tolerance. Below tol 1e-3 the density solve runs with
    # momentum (cpp/sph/solver.cpp kMomentum); before it, one free step of the 3D column stopped
    # at max_iter = 100 at tol 1e-4.
    r = column_at_rest("dfsph", d, tol=tol)
    assert r["v_rms"] < 0.02 * np.sqrt(2 * G * r["H"]), f"{d}D: rms speed {r['v_rms']:.3f} m/s"
    assert r["slope"] == pytest.approx(1, abs=0.1), f"{d}D: dp/dy = {r['slope']:.3f} rho0 g"
    assert r["unconverged"] == 0, f"{d}D: {r['unconverged']} free steps stopped at max_iter"


# At tol = 2e-3 the DFSPH column stays at rest too (the bounds above). It did not before the
# density solve's coarse correction (coarse_correction, on by default where tol > 1e-3;
# cpp/sph/coarse.h): 2D
# 0.073, 3D 0.079 m/s rms (WCSPH 0.024 / 0.048). Cause (bench/sph/sph_column_cycle.py --series):
# the solve stopped inside its tolerance band after its 2 minimum iterations, the column sank
# while its mean compression stayed below tol, and the step that reached tol built 3-5x the
# hydrostatic pressure, sending it back up, with the warm start carrying half of that into the
# next steps. The coarse correction rebuilds the hydrostatic (longest) mode at the start of every
# solve; measured after: 2D 0.021, 3D 0.042 m/s at 3.7 density iterations per step, and at
# tol 5e-3 (one-level: 2D 0.021, 3D 0.097) 0.021 / 0.040 at 3.0. The same column with
# coarse_correction=False is the test below.
@pytest.mark.parametrize("tol", [2e-3, 5e-3])
@pytest.mark.parametrize("d", [2, 3])
def test_dfsph_column_at_rest_loose_tol(d, tol):
    r = column_at_rest("dfsph", d, tol=tol)
    assert r["v_rms"] < 0.02 * np.sqrt(2 * G * r["H"]), f"{d}D: rms speed {r['v_rms']:.3f} m/s"
    assert r["slope"] == pytest.approx(1, abs=0.1), f"{d}D: dp/dy = {r['slope']:.3f} rho0 g"
    its = r["iterations"]
    assert its.mean() <= 10 and its.max() <= 60, f"{d}D: iterations per step mean {its.mean():.1f}, max {its.max()}"


# The one-level solve (coarse_correction=False, the paper's Jacobi alone) keeps the defect the
# coarse correction removes: strict, so that a change making it pass is noticed.
@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 15: without the coarse correction the column bounces at tol 2e-3")
@pytest.mark.parametrize("d", [2, 3])
def test_dfsph_column_at_rest_loose_tol_one_level(d):
    r = column_at_rest("dfsph", d, tol=2e-3, coarse_correction=False)
    assert r["v_rms"] < 0.02 * np.sqrt(2 * G * r["H"]), f"{d}D: rms speed {r['v_rms']:.3f} m/s"


def test_dfsph_warm_start_saves_iterations():
    # Bender and Koschier 2017, sec. 4.5: starting each solve from half the last step's
    # stiffnesses must take fewer iterations for the same density error (a collapsing column).
    s, a = 0.01, 0.1
    x = km.sph.block([0, 0], [a, 2 * a], s)
    totals = {}
    for warm in (0.0, 0.5):
        fluid = km.sph.Fluid(x, s, gravity=down(2), domain=([0, 0], [8 * a, 3 * a]), warm_start=warm)
        its = errs = 0
        for _ in range(50):
            st = fluid.step(fluid.stable_dt())
            its += st.iterations + st.divergence_iterations
            errs = max(errs, st.density_error)
        totals[warm] = its
        assert errs <= 1e-3, f"warm_start={warm}: density error {errs:.2e} above tol"
    assert totals[0.5] < 0.8 * totals[0.0], f"iterations with / without warm start: {totals}"


# ---------------------------------------------------------------- dam break

# Martin and Moyce (1952), Fig. 3, column of width a = 2.25 in and height 2a: surge-front
# position Z = z/a against T = t sqrt(2 g / a) (as digitised for PySPH's examples).
MARTIN_MOYCE = km.sph.martin_moyce()


def dam_break_front(method, spacing_ratio, a=0.1, points=MARTIN_MOYCE):
    """Front positions Z = z/a at the experiment's times, for a column of spacing a/ratio.

    The front is the x of the (ratio/4)-th farthest particle (at least the 3rd): a few spray
    particles ahead of the surge are not the front the experiment photographed.
    """
    s = a / spacing_ratio
    x = km.sph.block([0, 0], [a, 2 * a], s)
    fluid = km.sph.Fluid(x, s, gravity=down(2), method=method, domain=([0, 0], [8 * a, 3 * a]))
    Z = []
    for T, _ in points:
        fluid.advance(T / np.sqrt(2 * G / a) - fluid.time)
        Z.append(np.sort(fluid.x[:, 0])[-max(3, spacing_ratio // 4)] / a)
    return np.array(Z)


def dam_break_fronts(method, d, ratio, a=0.1, points=MARTIN_MOYCE[:4], viscosity=0.0, start_steps=0, walls=None):
    """Front Z = z/a at the experiment's times T: the column a x 2a (x a/2 deep in 3D) of
    `ratio` particles across in the tank 5a x 3a; the front is the x of the (ratio/4)-th
    farthest particle (at least the 3rd) + s/2. start_steps fixed steps of 5e-5 s come first
    (issue 15's set-up: the DFSPH warm start then met a 50x longer step)."""
    s = a / ratio
    size, box = [a, 2 * a] + [a / 2] * (d - 2), [5 * a, 3 * a] + [a / 2] * (d - 2)
    fluid = km.sph.Fluid(km.sph.block([0] * d, size, s), s, gravity=down(d), method=method, domain=([0] * d, box),
                         viscosity=viscosity, walls=walls)
    for _ in range(start_steps):
        fluid.step(5e-5)
    Z = []
    for T, _ in points:
        fluid.advance(T / np.sqrt(2 * G / a) - fluid.time)
        Z.append((np.sort(fluid.x[:, 0])[-max(3, ratio // 4)] + s / 2) / a)
    return np.array(Z)


# Dam-break fronts against Martin and Moyce (1952) to T = 2.5 (Z ~ 3), both methods, 2D (20
# particles across) and 3D (8 across). The SPH fronts lead the experiment (its gate took time to
# lift, its floor was not free-slip), by more as the resolution rises: measured 2D at 10 / 20
# across 7% / 14% (WCSPH) and 10% / 14% (DFSPH), 3D at 8 across 14% (WCSPH) and 12-17% (DFSPH),
# so 20% bounds the lead. The two methods solve the same equations and must agree to within the
# resolution error: twice the largest relative change of WCSPH's front between two resolutions
# of the same dimension (resolution_error): 2D from 10 to 20 across (measured 3.9%, so 7.9%),
# 3D from 8 to 16 across (measured 8.0%, at T = 2.0: Z = 2.49 -> 2.71, so 16%). Issue 15's
# DFSPH front was 67% ahead of WCSPH's. (Until issue 15's walls the 3D case took the 2D bound,
# which the mirrored walls met, +1.1%; the conservative walls' 8-across front is 8.1% ahead at
# T = 2.0, Z = 2.70, as far as WCSPH's own front moves from 8 to 16 across, and at 16 across
# DFSPH and WCSPH agree within 3.7%: a coarse-resolution difference, measured in 3D.)
@pytest.fixture(scope="module")
def wcsph_fronts():
    return {(2, 10): dam_break_fronts("wcsph", 2, 10), (2, 20): dam_break_fronts("wcsph", 2, 20),
            (3, 8): dam_break_fronts("wcsph", 3, 8), (3, 16): dam_break_fronts("wcsph", 3, 16)}


def resolution_error(wcsph_fronts, d):
    """Twice the largest relative change of WCSPH's front between the two resolutions of
    dimension d (2D: 10 -> 20 across, 3D: 8 -> 16)."""
    coarse, fine = {2: (10, 20), 3: (8, 16)}[d]
    wc, wf = wcsph_fronts[(d, coarse)], wcsph_fronts[(d, fine)]
    return 2 * np.max(np.abs(wf - wc) / wf)


# DFSPH's default walls (one stiffness per wall sample) and walls="mirror", largest gap to
# WCSPH: 2D at 20 across 2.2% / 1.5%, 3D at 8 across 8.1% / 1.9%.
@pytest.mark.parametrize("method, d, ratio, walls", [
    ("wcsph", 2, 20, None), ("dfsph", 2, 20, None), ("wcsph", 3, 8, None), ("dfsph", 3, 8, None),
    ("dfsph", 2, 20, "mirror"), ("dfsph", 3, 8, "mirror")])
def test_dam_break_front_against_experiment_and_wcsph(method, d, ratio, walls, wcsph_fronts):
    ref = MARTIN_MOYCE[:4, 1]
    Z = wcsph_fronts[(d, ratio)] if method == "wcsph" else dam_break_fronts(method, d, ratio, walls=walls)
    rel = Z / ref - 1
    assert np.all(np.abs(rel) < 0.2), f"{method} {d}D: relative front errors {np.round(rel, 3)}"
    assert np.all(np.diff(Z) > 0)
    resolution = resolution_error(wcsph_fronts, d)
    gap = np.abs(Z / wcsph_fronts[(d, ratio)] - 1)
    assert np.all(gap <= resolution), f"{method} {d}D: front differs from WCSPH by {np.round(gap, 3)} > {resolution:.3f}"


def test_dam_break_dfsph_after_small_fixed_steps(wcsph_fronts):
    # Issue 15's start: 10 steps of 5e-5 s, then advance() (first CFL step ~50x longer), with
    # nu = 1e-4. DFSPH's warm start carried the tiny steps' stiffnesses unscaled: its front was
    # at Z = 2.0 at T = 0.83 (experiment 1.22). Now within the bounds above.
    Z = dam_break_fronts("dfsph", 2, 20, viscosity=1e-4, start_steps=10)
    rel = Z / MARTIN_MOYCE[:4, 1] - 1
    assert np.all(np.abs(rel) < 0.2), f"relative front errors {np.round(rel, 3)}"
    w20 = wcsph_fronts[(2, 20)]
    resolution = resolution_error(wcsph_fronts, 2)
    assert np.all(np.abs(Z / w20 - 1) <= resolution), f"front {np.round(Z, 3)} vs WCSPH {np.round(w20, 3)}"


@pytest.mark.slow
@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_dam_break_front_martin_moyce(method):
    # 20 particles across the column, the whole record to Z ~ 5 (measured: within 22%). The
    # last point is chaotic: moving the initial positions by 1e-12 m spread WCSPH's error there
    # over 0.18-0.22 (main at 51ba820, four seeds), so rounding-level changes of the solver
    # move it by that much; the bound leaves room for the spread.
    Z = dam_break_front(method, 20)
    rel = Z / MARTIN_MOYCE[:, 1] - 1
    assert np.all(np.abs(rel) < 0.25), f"{method}: relative front errors {np.round(rel, 3)}"


# ---------------------------------------------------------------- stability

def test_wcsph_dt_far_above_cfl_raises_divergence():
    s = 0.01
    x = km.sph.block([0, 0], [0.2, 0.2], s)
    fluid = km.sph.Fluid(x, s, gravity=down(2), method="wcsph", domain=([0, 0], [0.4, 0.4]))
    dt = 30 * fluid.stable_dt()
    with pytest.raises(km.StabilityError, match="dt"):
        fluid.step(dt)
    with pytest.raises(km.DivergenceError, match="dt"):
        for _ in range(2000):
            fluid.step(dt, check=False)
            assert np.isfinite(fluid.x).all() and np.isfinite(fluid.v).all()


@pytest.mark.parametrize("d", [2, 3])
def test_wcsph_stability_limit_is_where_it_diverges(d):
    """stability_limit() is a true bound, not a guess: a dam break at 1.5 times WCSPH's acoustic
    limit runs 0.3 s (checked off), at 3 times it diverges within 0.3 s; check=True refuses the
    step above the limit, naming dt, and takes the one below it."""
    s = 0.01 if d == 2 else 0.02
    x = km.sph.block([0] * d, [0.2] * d, s)

    def run(factor):
        fluid = km.sph.Fluid(x, s, gravity=down(d), method="wcsph", domain=([0] * d, [0.4] * d))
        dt = factor * fluid.stability_limit()
        for _ in range(int(0.3 / dt)):
            fluid.step(dt, check=False)
        return fluid

    fluid = run(1.5)
    assert np.isfinite(fluid.x).all() and fluid.density_error() < 1e-2
    with pytest.raises(km.DivergenceError):
        run(3.0)
    fluid = km.sph.Fluid(x, s, gravity=down(d), method="wcsph", viscosity=0.5, domain=([0] * d, [0.4] * d))
    limit = fluid.stability_limit()
    assert limit == pytest.approx(min(s / fluid.speed_of_sound, 2 / (19.3 if d == 2 else 21.4) * s * s / 0.5))
    with pytest.raises(km.StabilityError, match="dt"):
        fluid.step(1.01 * limit)
    fluid.step(0.99 * limit)
    assert km.sph.Fluid(x, s, method="dfsph", domain=([0] * d, [0.4] * d)).stability_limit() == np.inf


def test_dfsph_large_dt_stays_bounded():
    s = 0.01
    x = km.sph.block([0, 0], [0.2, 0.2], s)
    fluid = km.sph.Fluid(x, s, gravity=down(2), method="dfsph", domain=([0, 0], [0.4, 0.4]))
    try:
        for _ in range(40):
            fluid.step(0.02)  # 4x the largest step advance() would take
    except km.DivergenceError:
        return
    assert np.isfinite(fluid.x).all()
    assert np.all((fluid.x >= 0) & (fluid.x <= 0.4))
    assert np.abs(fluid.v).max() < 10 * np.sqrt(2 * G * 0.4)


@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_overlapping_and_outside_particles(method):
    s = 0.01
    x = km.sph.block([0.05, 0.05], [0.15, 0.15], s)
    x = np.concatenate([x, x + 0.3 * s, [[-0.1, 0.05], [0.5, 0.5]], x[:3]])  # overlaps, outside
    fluid = km.sph.Fluid(x, s, gravity=down(2), method=method, domain=([0, 0], [0.3, 0.3]))
    try:
        fluid.advance(0.2)
    except km.DivergenceError:
        return
    assert np.isfinite(fluid.x).all() and np.isfinite(fluid.v).all()
    assert np.all((fluid.x >= 0) & (fluid.x <= 0.3))


@pytest.mark.parametrize("d", [2, 3])
def test_single_particle_free_fall(d):
    # No neighbours: symplectic Euler gives y_n = y0 - g dt^2 n(n+1)/2 exactly.
    x0 = np.full((1, d), 0.5)
    for method in ("wcsph", "dfsph"):
        fluid = km.sph.Fluid(x0, 0.01, gravity=down(d), method=method)
        dt, n = 1e-3, 100
        for _ in range(n):
            fluid.step(dt)
        assert fluid.x[0, 1] == pytest.approx(0.5 - G * dt**2 * n * (n + 1) / 2, rel=1e-12)
        assert fluid.v[0, 1] == pytest.approx(-G * dt * n, rel=1e-12)


# advance() warns (RuntimeWarning, an error under pytest) when a DFSPH pressure solve stops at
# max_iter. At 2.5 mm the column below reaches the cap in 3 of its 17 steps (density error
# 1.4e-3 > tol 1e-3) and its fine run is not at rest at all: see the next test.
@pytest.mark.parametrize("spacing", [0.05, pytest.param(0.0025, marks=pytest.mark.xfail(
    strict=True, raises=RuntimeWarning, reason="issue 15: the density solve stops at max_iter (3 of 17 steps)"))])
def test_coarse_and_fine_spacing(spacing):
    L = 0.1
    x = km.sph.block([0, 0], [L, L / 2], spacing)
    fluid = km.sph.Fluid(x, spacing, gravity=down(2), domain=([0, 0], [L, L]))
    fluid.advance(0.05)
    assert np.isfinite(fluid.x).all() and fluid.density_error() < 0.01


# A column at rest that fills its closed tank (0.1 m wide, 0.05 m deep, inviscid) has nowhere to
# go: what it may do is settle (WCSPH compresses by ~(v/c)^2, the lattice rearranges), which
# releases potential energy, never gains it. Checked every step of 0.3 s at the steps
# stable_dt() gives: kinetic + potential energy at most 1% of the available energy (e0 minus
# the lowest possible state, as test_long_run_without_energy_gain) above its start; speed below
# sqrt(2 g H) (0.99 m/s, a fall over the whole depth: a particle cannot be faster without
# energy from elsewhere); each DFSPH solve within its tolerance (not stopped at max_iter); the
# density error of the positions reached below 1%.
# WCSPH keeps its energy (measured over 0.3 s: gain -0.000 of the available energy in all three
# cases, top speed 0.11 / 0.10 / 0.16 m/s): its box walls carry the pressure of their own
# density (cpp/sph/solver.cpp, "WCSPH's walls"), the force is the gradient of the fluid's
# energy walls included. Before, the walls mirrored the pressure, 2 P_i B_i, twice the walls'
# share of that gradient: +188% / +123% / +174%, 5.0 / 2.6 / 3.9 m/s.
# DFSPH's default walls give each wall sample one stiffness, the Shepard average of its fluid
# neighbours' (a force of constraint form; issue 15): -0.0% (0.09 m/s) at 2D 5 mm, -0.1%
# (0.09 m/s) in 3D, +0.8% (0.35 m/s) at 2D 2.5 mm, where the first steps from the lattice still
# stop at max_iter (mean compression 1.2e-3 against tol 1e-3 after 100 iterations, as in
# test_coarse_and_fine_spacing at that spacing) and the positions reached are compressed by up
# to 2.8% at t = 0.06 s: at 2.5 mm the column's bottom rows rearrange at 1-15 g, the density
# solve's linear prediction rho + dt D rho / Dt misses their second-order compression
# (predicted 1e-3, reached 3%), and the next step removes it by velocities from nowhere.
# walls="mirror" (the default before) mirrors the stiffness (2 k_i B_i, apply_kappa), twice the
# walls' share of the energy gradient, and gains: 2D 2.5 mm +37% (1.74 m/s, 3 solves at
# max_iter), 2D 5 mm +1.9%, 3D 5 mm +5.6%. Strict, so that a fix is noticed.
_MIRROR_GAINS = pytest.mark.xfail(strict=True, reason="issue 15: DFSPH's mirrored walls are not conservative")
_DFSPH_FINE = pytest.mark.xfail(strict=True, reason="issue 15: DFSPH at 2.5 mm: the first solves from the lattice stop at max_iter, 2.8% compression")
FILLED = [pytest.param(method, d, s, None, id=f"{method}-{d}d-{s}", marks=[_DFSPH_FINE] if method == "dfsph" and s == 0.0025 else [])
          for method in ("dfsph", "wcsph") for d, s in ((2, 0.0025), (2, 0.005), (3, 0.005))]
FILLED += [pytest.param("dfsph", d, s, "mirror", id=f"dfsph-mirror-{d}d-{s}", marks=[_MIRROR_GAINS])
           for d, s in ((2, 0.0025), (2, 0.005), (3, 0.005))]


@pytest.mark.parametrize("method, d, s, walls", FILLED)
def test_column_filling_its_tank_stays_at_rest(method, d, s, walls):
    L, H = 0.1, 0.05
    upper = [L] * d
    upper[1] = H
    fluid = km.sph.Fluid(km.sph.block([0] * d, upper, s), s, gravity=down(d), method=method,
                         domain=([0] * d, [L] * d), walls=walls)
    mass = fluid.mass

    def energy():
        return fluid.kinetic_energy() + mass * G * fluid.x[:, 1].sum()

    e0 = energy()
    available = e0 - mass * G * (s / 2) * fluid.n
    end = 0.3
    while fluid.time < end - 1e-12:
        st = fluid.step(min(fluid.stable_dt(), end - fluid.time))
        where = f"{method} {d}D s={s} step {fluid.steps} (t = {fluid.time:.4f} s)"
        assert st.density_converged and st.divergence_converged, f"{where}: a pressure solve stopped at max_iter"
        assert st.max_speed < np.sqrt(2 * G * H), f"{where}: speed {st.max_speed:.3f} m/s"
        gain = (energy() - e0) / available
        assert gain < 0.01, f"{where}: energy rose by {gain:.2%} of the available energy"
        assert fluid.density_error() < 0.01, f"{where}: density error {fluid.density_error():.2e}"


def test_long_run_without_energy_gain():
    # A column collapsing in a closed tank: kinetic + potential energy may only decrease.
    s = 0.01
    x = km.sph.block([0, 0], [0.1, 0.2], s)
    fluid = km.sph.Fluid(x, s, gravity=down(2), method="dfsph", domain=([0, 0], [0.3, 0.3]))
    mass = fluid.mass

    def energy():
        return fluid.kinetic_energy() + mass * G * fluid.x[:, 1].sum()

    e0 = energy()
    floor = mass * G * (s / 2) * fluid.n  # potential energy of the lowest possible state
    worst = -np.inf
    for _ in range(20):
        fluid.advance(0.1)
        worst = max(worst, (energy() - e0) / (e0 - floor))
    assert worst < 0.01, f"energy rose by {worst:.2%} of the available energy"


# ---------------------------------------------------------------- state views and determinism

def test_state_views_are_zero_copy_and_survive_the_fluid():
    s = 0.01
    x = km.sph.block([0, 0], [0.1, 0.1], s)
    fluid = km.sph.Fluid(x, s, method="wcsph", domain=([0, 0], [0.2, 0.2]), gravity=[0, 0], speed_of_sound=50,
                         reorder_every=1)
    xv, vv = fluid.x, fluid.v
    assert xv.shape == (100, 2) and vv.flags.writeable and not xv.flags.owndata
    vv[:, 0] = 1.0  # writing into the view moves the fluid
    fluid.step(1e-4)
    assert xv[:, 0].mean() == pytest.approx(x[:, 0].mean() + 1e-4, abs=1e-6)
    # Reordering permutes rows in place: ids maps rows back to the input order.
    ids = fluid.ids.copy()
    assert sorted(ids) == list(range(100))
    assert np.abs(xv - (x[ids] + [1e-4, 0])).max() < 1e-5
    del fluid
    assert np.isfinite(xv.sum())  # the views keep their owner alive


@pytest.mark.parametrize("method", ["dfsph", "wcsph"])
def test_step_stats_split_the_step_time(method):
    # StepStats says where a step's wall time went: the neighbour search, the kernel pass and
    # the pressure solves are disjoint parts of the step, so they are >= 0 and sum to at most
    # the step's seconds; the kernel pass and the solve always run.
    s = 0.01
    fluid = km.sph.Fluid(km.sph.block([0, 0, 0], [0.1, 0.2, 0.1], s), s, method=method, gravity=down(3),
                         domain=([0, 0, 0], [0.4, 0.3, 0.1]))
    for _ in range(5):
        st = fluid.step(fluid.stable_dt())
        parts = (st.search_seconds, st.kernel_seconds, st.solve_seconds)
        assert min(parts) >= 0 and st.kernel_seconds > 0 and st.solve_seconds > 0, parts
        assert sum(parts) <= st.seconds, (parts, st.seconds)


def test_runs_are_bitwise_reproducible():
    s = 0.01
    x = km.sph.block([0, 0], [0.1, 0.2], s)
    results = []
    for _ in range(2):
        fluid = km.sph.Fluid(x, s, gravity=down(2), domain=([0, 0], [0.3, 0.3]), viscosity=1e-3)
        fluid.advance(0.05)
        results.append(fluid.x.copy())
    np.testing.assert_array_equal(results[0], results[1])


@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_runs_do_not_depend_on_the_thread_count(method):
    # Large enough (> 4096 particles, the parallel grain) that every pass, the neighbour search
    # and the reductions really split across threads; walls and a free surface included.
    s = 0.005
    x = km.sph.block([0, 0], [0.33, 0.33], s)
    assert len(x) > 4096
    threads = km.get_num_threads()
    results = []
    try:
        for t in (1, 2):
            km.set_num_threads(t)
            fluid = km.sph.Fluid(x, s, gravity=down(2), method=method, domain=([0, 0], [0.6, 0.4]))
            dt = 0.5 * fluid.stable_dt()
            stats = [fluid.step(dt) for _ in range(4)]
            results.append((fluid.x.copy(), fluid.v.copy(), fluid.density.copy(),
                            [st.iterations for st in stats]))
    finally:
        km.set_num_threads(threads)
    (x1, v1, rho1, it1), (x2, v2, rho2, it2) = results
    assert it1 == it2, (it1, it2)
    for name, a, b in (("x", x1, x2), ("v", v1, v2), ("density", rho1, rho2)):
        assert np.array_equal(a, b), f"{method} {name}: 1 vs 2 threads differ by {np.abs(a - b).max():.3e}"


@pytest.mark.parametrize("d", [2, 3])
def test_coarse_correction_engages_and_does_not_depend_on_the_thread_count(d):
    # A column at rest at tol 2e-3, where the density solve's warm start ends within tol and its
    # coarse correction (cpp/sph/coarse.h: chunked Galerkin sums, > 4096 particles) runs: 1 and 2
    # threads bitwise equal, and the run differs from the one-level solve's (it did run).
    s = 0.005 if d == 2 else 0.012
    size = [0.5, 0.25] if d == 2 else [0.24, 0.3, 0.12]
    x = km.sph.block([0] * d, size, s)
    assert len(x) > 4096
    box = list(size)
    box[1] *= 2
    threads = km.get_num_threads()
    results = {}
    try:
        for t, coarse in ((1, True), (2, True), (2, False)):
            km.set_num_threads(t)
            fluid = km.sph.Fluid(x, s, gravity=down(d), domain=([0] * d, box), tol=2e-3, coarse_correction=coarse)
            stats = [fluid.step(fluid.stable_dt()) for _ in range(6)]
            results[t, coarse] = (fluid.x.copy(), fluid.v.copy(), [st.iterations for st in stats])
    finally:
        km.set_num_threads(threads)
    (x1, v1, it1), (x2, v2, it2), (x0, _, _) = results[1, True], results[2, True], results[2, False]
    assert it1 == it2, (it1, it2)
    assert np.array_equal(x1, x2) and np.array_equal(v1, v2), f"{d}D: 1 vs 2 threads differ by {np.abs(x1 - x2).max():.3e}"
    assert not np.array_equal(x1, x0), f"{d}D: the coarse correction never ran"


def test_coarse_correction_default_is_on_only_above_tol_1e_3():
    # None (auto): the two-level solve where tol > 1e-3 (where the one-level solve let a column
    # at rest bounce), the one-level solve at tighter tolerances (bitwise main's).
    s = 0.02
    x = km.sph.block([0, 0], [1.0, 0.5], s)
    for tol, same_as in ((1e-3, False), (2e-3, True)):
        runs = {}
        for option in (None, True, False):
            fluid = km.sph.Fluid(x, s, gravity=down(2), domain=([0, 0], [1, 1]), tol=tol, coarse_correction=option)
            for _ in range(15):
                fluid.step(fluid.stable_dt())
            runs[option] = fluid.x.copy()
        assert np.array_equal(runs[None], runs[same_as]), f"tol {tol}: default is not coarse_correction={same_as}"
    assert not np.array_equal(runs[True], runs[False]), "tol 2e-3: the coarse correction never ran"
    assert km.sph.Fluid(x, s).config.coarse_correction == -1


@pytest.mark.parametrize("method", ["wcsph", "dfsph"])
def test_avx2_and_baseline_runs_are_bitwise_equal(method, monkeypatch):
    # The light passes' row sums (3D) and the kernel pass's kernel values take AVX2 where the
    # CPU has it; KINEMA_SIMD=baseline (read when the solver is built) forces the portable code.
    # Both do the same operations in the same order, so whole runs agree bit for bit
    # (tests/cpp/test_sph_rows.cpp checks the row sums and kernel values themselves, and skips
    # where the CPU has no AVX2).
    s = 0.02
    x = km.sph.block([0, 0, 0], [0.2, 0.3, 0.2], s)
    domain = ([0, 0, 0], [0.5, 0.4, 0.2])
    results = []
    for simd in ("baseline", None):
        if simd:
            monkeypatch.setenv("KINEMA_SIMD", simd)
        else:
            monkeypatch.delenv("KINEMA_SIMD", raising=False)
        fluid = km.sph.Fluid(x, s, gravity=down(3), method=method, domain=domain)
        dt = 0.5 * fluid.stable_dt()
        stats = [fluid.step(dt) for _ in range(4)]
        results.append((fluid.x.copy(), fluid.v.copy(), [st.iterations for st in stats]))
    (x1, v1, it1), (x2, v2, it2) = results
    assert it1 == it2, (it1, it2)
    for name, a, b in (("x", x1, x2), ("v", v1, v2)):
        assert np.array_equal(a, b), f"{method} {name}: AVX2 vs baseline differ by {np.abs(a - b).max():.3e}"


# ---------------------------------------------------------------- bad input

@pytest.mark.parametrize("kwargs, match", [
    (dict(positions=np.zeros((4, 4))), "positions"),
    (dict(positions=[[0.0, np.nan]]), "positions"),
    (dict(spacing=0), "spacing"),
    (dict(spacing=-1), "spacing"),
    (dict(method="pcisph"), "method"),
    (dict(rho0=0), "rho0"),
    (dict(viscosity=-1), "viscosity"),
    (dict(gravity=[0, 0, -9.81]), "gravity"),
    (dict(domain=([0, 0], [1, -1])), "domain"),
    (dict(domain=[0, 1]), "domain"),
    (dict(domain=([0, 0, 0], [1, 1, 1])), "domain"),
    (dict(boundary=np.zeros((3, 3))), "boundary"),
    (dict(speed_of_sound=0), "speed_of_sound"),
    (dict(velocity=np.zeros((2, 2))), "velocity"),
    (dict(max_iter=0), "max_iter"),
    (dict(reorder_every=-1), "reorder_every"),
    (dict(walls="akinci"), "walls"),
    (dict(walls="shepard", method="wcsph"), "walls"),
    (dict(walls="mirror", method="wcsph"), "walls"),
])
def test_bad_arguments_raise_value_error(kwargs, match):
    args = dict(positions=[[0.5, 0.5]], spacing=0.01)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        km.sph.Fluid(args.pop("positions"), args.pop("spacing"), **args)


def test_bad_calls_raise_value_error():
    fluid = km.sph.Fluid([[0.5, 0.5]], 0.01)
    for bad in (0, -1, np.nan, np.inf, "x"):
        with pytest.raises(ValueError, match="dt"):
            fluid.step(bad)
    with pytest.raises(ValueError, match="cfl"):
        fluid.advance(0.1, cfl=0)
    with pytest.raises(ValueError, match="radius"):
        km.sph.neighbor_pairs(np.zeros((3, 2)), 0)
    with pytest.raises(ValueError, match="points"):
        km.sph.neighbor_pairs(np.zeros((3, 4)), 1)
    with pytest.raises(ValueError, match="d"):
        km.sph.kernel(0.1, 1.0, 4)
    with pytest.raises(ValueError, match="derivative"):
        km.sph.kernel(0.1, 1.0, 3, derivative=3)
    with pytest.raises(ValueError, match="spacing"):
        km.sph.block([0, 0], [1, 1], 0)
    with pytest.raises(ValueError, match="layers"):
        km.sph.box_boundary([0, 0], [1, 1], 0.1, layers=0)


def test_nan_written_into_state_raises_divergence():
    fluid = km.sph.Fluid(km.sph.block([0, 0], [0.1, 0.1], 0.01), 0.01)
    fluid.v[3, 1] = np.nan
    with pytest.raises(km.DivergenceError, match="non-finite"):
        fluid.step(1e-3)


# ---------------------------------------------------------------- example

def test_dam_break_example_smoke(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "sph_dam_break_3d.py"
    spec = importlib.util.spec_from_file_location("sph_dam_break_3d", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert example.main(["--out", str(tmp_path), "--spacing", "0.06", "--frames", "2", "--no-video"]) == 0
    data = (tmp_path / "frame_0002.ply").read_bytes()
    header, body = data.split(b"end_header\n")
    n = int(header.split(b"element vertex ")[1].split(b"\n")[0])
    xyz = np.frombuffer(body, "<f4").reshape(n, 4)
    assert np.isfinite(xyz).all() and (xyz[:, 1] >= 0).all()
    # The VTK file holds the same points (big-endian float32 after the POINTS line).
    vtk = (tmp_path / "frame_0002.vtk").read_bytes()
    start = vtk.index(b"POINTS %d float\n" % n) + len(b"POINTS %d float\n" % n)
    pts = np.frombuffer(vtk[start:start + 12 * n], ">f4").reshape(n, 3)
    np.testing.assert_array_equal(pts, xyz[:, :3])
    assert b"VERTICES %d %d" % (n, 2 * n) in vtk


# ---------------------------------------------------------------- obstacles other than boxes


def _nearest(points):
    from scipy.spatial import cKDTree

    return cKDTree(points).query(points, 2)[0][:, 1]


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("fluid", ["outside", "inside"])
def test_sphere_boundary_layers_radii_and_spacing(d, fluid):
    c, r, s = np.full(d, 0.2), 0.3, 0.02
    b = km.sph.sphere_boundary(c, r, s, layers=3, fluid=fluid)
    rad = np.linalg.norm(b - c, axis=1)
    sign = -1 if fluid == "outside" else 1
    total = 0
    for k in range(3):
        rk = r + sign * (k + 0.5) * s
        layer = b[np.abs(rad - rk) < 1e-12]
        area = 2 * np.pi * rk if d == 2 else 4 * np.pi * rk**2
        assert len(layer) == round(area / s ** (d - 1))  # one sample per spacing^(d-1) of surface
        nn = _nearest(layer) / s
        # even spreading: equal arcs on a circle (chord 2 r sin(pi/n) ~ s); the Fibonacci lattice's
        # nearest neighbours lie within 0.85-1.0 s for an area of s^2 per sample
        lo, hi = (0.99, 1.01) if d == 2 else (0.85, 1.05)
        assert lo <= nn.min() and nn.max() <= hi, (nn.min(), nn.max())
        total += len(layer)
    assert total == len(b)  # nothing else
    with pytest.raises(ValueError, match="fluid"):
        km.sph.sphere_boundary(c, r, s, fluid="above")
    with pytest.raises(ValueError, match="radius"):
        km.sph.sphere_boundary(c, -1.0, s)
    # a sphere smaller than its layers ends in one centre sample
    small = km.sph.sphere_boundary(c, 1.2 * s, s, layers=3)
    assert np.allclose(small[-1], c) and len(small) >= 2


def test_mesh_boundary_of_a_box_is_the_lattice_band_inside_it():
    """The surface of a tet-meshed unit cube (km.mesh.surface): the samples are exactly the
    points of the centred spacing-0.1 lattice within 2 spacings of the walls, inside."""
    v, tets = km.fem.box_mesh((0, 0, 0), (1, 1, 1), 3)
    faces = km.mesh.surface(v, tets)
    b = km.sph.mesh_boundary(v, faces, 0.1, layers=2)
    assert len(b) == 10**3 - 6**3  # the 6^3 points deeper than 0.2 are left out
    assert ((b > 0) & (b < 1)).all()
    depth = np.minimum(b, 1 - b).min(axis=1)
    assert depth.max() < 0.2 and depth.min() == pytest.approx(0.05)
    np.testing.assert_allclose(_nearest(b), 0.1, rtol=1e-12)
    # a container instead: the band outside the walls
    out = km.sph.mesh_boundary(v, faces, 0.1, layers=2, fluid="inside")
    assert len(out) > 0 and (((out < 0) | (out > 1)).any(axis=1)).all()
    assert (np.maximum(-out, out - 1).max(axis=1) < 0.2 + 1e-12).all()


def test_mesh_boundary_of_a_polygon_in_2d():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])  # counter-clockwise: interior on the left
    b = km.sph.mesh_boundary(square, edges, 0.1)
    assert len(b) == 10**2 - 6**2
    assert ((b > 0) & (b < 1)).all()
    with pytest.raises(ValueError, match="faces"):
        km.sph.mesh_boundary(square, edges[:, :1], 0.1)
    with pytest.raises(ValueError, match="faces"):
        km.sph.mesh_boundary(square, edges + 10, 0.1)


def _sphere_mesh(c, r, n=400):
    """A closed triangle mesh of the sphere (convex hull of Fibonacci points), faces outward."""
    from scipy.spatial import ConvexHull

    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (3 - np.sqrt(5)) * np.arange(n)
    p = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    f = ConvexHull(p).simplices.copy()
    normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    inward = np.einsum("ij,ij->i", normal, p[f].mean(1)) < 0
    f[inward] = f[inward][:, ::-1]
    return c + r * p, f


def test_mesh_boundary_of_a_sphere_mesh_lies_inside_it_within_the_band():
    c, r, s = np.array([0.5, 0.5, 0.5]), 0.3, 0.03
    v, f = _sphere_mesh(c, r)
    b = km.sph.mesh_boundary(v, f, s, layers=2)
    rad = np.linalg.norm(b - c, axis=1)
    # the inscribed polyhedron lies within r (1 - cos of its edge angle) of the sphere
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).max()
    sag = r - np.sqrt(r**2 - (edge / 2) ** 2)
    assert rad.max() < r and rad.min() > r - 2 * s - sag
    shell = 4 / 3 * np.pi * (r**3 - (r - 2 * s) ** 3)
    assert len(b) == pytest.approx(shell / s**3, rel=0.1)  # one lattice point per s^3


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("sampler", ["sphere", "mesh"])
def test_fluid_column_on_a_sphere_obstacle_does_not_leak(d, sampler):
    """A water column falls onto a sphere (circle) obstacle in a closed box and flows around
    it: no particle crosses the first boundary layer (radius r - spacing/2). Without the
    obstacle the same particles fall through where the sphere would be (the test can fail)."""
    s = 0.02 if d == 2 else 0.04
    c, r = np.array([0.5, 0.3, 0.5][:d]), (0.15 if d == 2 else 0.2)
    x = km.sph.block([0.38, 0.5, 0.38][:d], [0.62, 0.9, 0.62][:d], s)
    if sampler == "sphere":
        obstacle = km.sph.sphere_boundary(c, r, s)
    elif d == 2:
        t = 2 * np.pi * np.arange(96) / 96
        poly = c + r * np.stack([np.cos(t), np.sin(t)], 1)
        obstacle = km.sph.mesh_boundary(poly, np.stack([np.arange(96), (np.arange(96) + 1) % 96], 1), s)
    else:
        obstacle = km.sph.mesh_boundary(*_sphere_mesh(c, r), s)
    closest = {}
    for with_obstacle in (True, False):
        fluid = km.sph.Fluid(x, s, gravity=np.r_[0, -9.81, 0][:d], domain=(np.zeros(d), np.ones(d)),
                             boundary=obstacle if with_obstacle else None)
        m = np.inf
        for _ in range(10):
            fluid.advance(0.05)
            m = min(m, np.linalg.norm(fluid.x - c, axis=1).min())
        assert np.isfinite(fluid.x).all()
        closest[with_obstacle] = m
    assert closest[True] > r - 0.5 * s, (closest, r - 0.5 * s)
    assert closest[True] < r + 1.5 * s  # the fluid did reach the obstacle
    assert closest[False] < 0.5 * r, closest
