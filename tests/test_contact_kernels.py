"""Contact kernels (km.contact): the closest-point distance formulas with their gradients and
Hessians against central finite differences, the region classification against brute-force
sampling, the IPC barrier, and the additive CCD against densely sampled trajectories."""

import numpy as np
import pytest

import kinema as km

C = km._core.contact
KINDS = {"pp": 2, "pe": 3, "pt": 4, "ee": 4}


def fd_derivatives(kind, v, eps):
    k = KINDS[kind]
    g = np.zeros(3 * k)
    H = np.zeros((3 * k, 3 * k))
    for i in range(3 * k):
        vp, vm = v.ravel().copy(), v.ravel().copy()
        vp[i] += eps
        vm[i] -= eps
        dp, gp, _ = C.pair_distance(kind, vp.reshape(k, 3))
        dm, gm, _ = C.pair_distance(kind, vm.reshape(k, 3))
        g[i] = (dp - dm) / (2 * eps)
        H[:, i] = (gp - gm) / (2 * eps)
    return g, H


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_distance_gradient_and_hessian_match_central_differences(kind):
    # Central differences with eps = 1e-5 on O(1) coordinates: truncation eps^2 |f'''| ~ 1e-10
    # and rounding 1e-16 / eps ~ 1e-11 relative, far below the 1e-6 asserted.
    rng = np.random.default_rng(7)
    for _ in range(10):
        v = rng.normal(size=(KINDS[kind], 3))
        d, g, H = C.pair_distance(kind, v)
        g_fd, H_fd = fd_derivatives(kind, v, 1e-5)
        scale_g, scale_H = np.abs(g).max(), np.abs(H).max()
        assert np.abs(g - g_fd).max() <= 1e-6 * scale_g, (kind, np.abs(g - g_fd).max(), scale_g)
        assert np.abs(H - H_fd).max() <= 1e-6 * scale_H, (kind, np.abs(H - H_fd).max(), scale_H)
        assert np.allclose(H, H.T, atol=1e-12 * scale_H)
        # Translation invariance: the gradient sums to zero over the vertices, and the Hessian
        # annihilates a rigid translation.
        assert np.abs(g.reshape(-1, 3).sum(0)).max() <= 1e-12 * scale_g
        assert np.abs(H @ np.tile([1.0, 2.0, 3.0], KINDS[kind])).max() <= 1e-10 * scale_H


def sampled_point_triangle(p, t0, t1, t2, n=400):
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    keep = u + v <= 1
    pts = t0 + u[keep, None] * (t1 - t0) + v[keep, None] * (t2 - t0)
    return np.min(np.sum((pts - p) ** 2, axis=1))


def test_point_triangle_distance_matches_brute_force_over_all_regions():
    rng = np.random.default_rng(3)
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    pts = rng.uniform(-1, 2, size=(30, 3))
    exact = C.point_triangle_distance(pts, *(np.repeat(t[None], len(pts), 0) for t in tri))
    for p, d in zip(pts, exact):
        sampled = sampled_point_triangle(p, *tri)
        # The sampled minimum is an upper bound; the lattice (spacing 1/400, so a point within
        # h = 1/400 * sqrt(2) / 2 of the true closest point) bounds its excess by 2 sqrt(d) h + h^2.
        h = np.sqrt(2) / 800
        assert d <= sampled + 1e-15
        assert sampled - d <= 2 * np.sqrt(d) * h + h * h, (p, d, sampled)


def test_edge_edge_distance_matches_brute_force_including_parallel_edges():
    rng = np.random.default_rng(4)
    s = np.linspace(0, 1, 801)
    cases = [rng.normal(size=(4, 3)) for _ in range(20)]
    cases.append(np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 0.3, 0], [1.5, 0.3, 0]]))  # parallel, overlapping
    cases.append(np.array([[0.0, 0, 0], [1, 0, 0], [2.0, 0.0, 0], [3, 0.0, 0]]))    # collinear, apart
    for a0, a1, b0, b1 in cases:
        d = C.edge_edge_distance(a0[None], a1[None], b0[None], b1[None])[0]
        pa = a0 + s[:, None] * (a1 - a0)
        pb = b0 + s[:, None] * (b1 - b0)
        sampled = np.min(np.sum((pa[:, None] - pb[None]) ** 2, axis=2))
        h = (np.linalg.norm(a1 - a0) + np.linalg.norm(b1 - b0)) / 1600
        assert d <= sampled + 1e-14
        assert sampled - d <= 2 * np.sqrt(d) * h + h * h + 1e-14, (d, sampled)


def test_barrier_derivatives_and_smooth_activation():
    dhat2 = 1e-6
    for d in np.geomspace(1e-12, 0.999e-6, 25):
        b, b1, b2 = C.barrier(d, dhat2)
        eps = 1e-6 * d
        bp, b1p, _ = C.barrier(d + eps, dhat2)
        bm, b1m, _ = C.barrier(d - eps, dhat2)
        assert abs((bp - bm) / (2 * eps) - b1) <= 1e-6 * abs(b1) + 1e-20
        assert abs((b1p - b1m) / (2 * eps) - b2) <= 1e-5 * abs(b2) + 1e-20
        assert b > 0 and b1 < 0 and b2 > 0
    # C^2 at dhat: value, slope and curvature vanish there; 0 beyond.
    assert C.barrier(dhat2, dhat2) == (0.0, 0.0, 0.0)
    b, b1, b2 = C.barrier(dhat2 * (1 - 1e-6), dhat2)
    assert abs(b) < 1e-20 and abs(b1) < 1e-15 and abs(b2) < 1e-4


def sampled_min_distance(kind, x0, x1, t_end, n=2000):
    f = C.point_triangle_distance if kind == "pt" else C.edge_edge_distance
    ts = np.linspace(0, t_end, n)
    y = x0[None] + ts[:, None, None] * (x1 - x0)[None]
    return np.sqrt(f(y[:, 0], y[:, 1], y[:, 2], y[:, 3]).min())


@pytest.mark.parametrize("kind", ["pt", "ee"])
def test_ccd_never_passes_through_contact(kind):
    # Random linear trajectories aimed through each other: the time of impact must come before
    # any sampled contact, the pair must stay apart up to it, and a pair that does not come
    # close must be allowed the whole step.
    rng = np.random.default_rng(11)
    hits = 0
    for _ in range(60):
        x0 = rng.normal(size=(4, 3))
        x1 = x0 + rng.normal(size=(4, 3)) * 2
        if kind == "pt":
            # Aim the point through the triangle's centroid at t = 0.5.
            middle = 0.5 * (x0[1:].mean(0) + x1[1:].mean(0))
            x1[0] = 2 * middle - x0[0]
        t = C.ccd(kind, x0, x1, 1.0)
        assert 0 <= t <= 1
        assert sampled_min_distance(kind, x0, x1, t) > 0
        if t < 1:
            hits += 1
    assert hits > 10
    apart = np.array([[0.0, 0, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    away = apart.copy()
    away[0] = [0, 0, -4]  # the first vertex moves away from the others
    assert C.ccd(kind, apart, away, 1.0) == 1.0


def test_ccd_point_through_triangle_stops_before_the_plane():
    tri = np.array([[-1.0, -1, 0], [2, -1, 0], [-1, 2, 0]])
    x0 = np.vstack([[0.1, 0.1, 1.0], tri])
    x1 = np.vstack([[0.1, 0.1, -1.0], tri])  # crosses the plane at t = 0.5
    t = C.ccd("pt", x0, x1, 1.0)
    assert 0.4 < t < 0.5
    # Stops at about a tenth of the initial gap: 1 - 2 t = remaining height in [0, 0.1].
    assert 0 < 1 - 2 * t <= 0.1 + 1e-12


def test_exact_distances_equal_their_region_formula():
    # point_triangle_distance / edge_edge_distance compute the distance from the closest points
    # found by the region search; it must equal the smooth formula of that region (the one the
    # barrier differentiates) to rounding, ~1e-15 relative.
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    cases = [  # point, formula, vertices the formula reads
        ([0.2, 0.3, 0.7], "pt", lambda p: [p, *tri]),  # above the interior: the plane
        ([0.5, -0.4, 0.3], "pe", lambda p: [p, tri[0], tri[1]]),  # beyond edge (t0, t1)
        ([-0.5, -0.5, 0.2], "pp", lambda p: [p, tri[0]]),  # beyond vertex t0
    ]
    for p, kind, verts in cases:
        p = np.array(p)
        exact = C.point_triangle_distance(p[None], *(t[None] for t in tri))[0]
        formula = C.pair_distance(kind, np.array(verts(p)))[0]
        assert exact == pytest.approx(formula, rel=1e-14), (kind, exact, formula)
    a0, a1 = np.array([0.0, 0, 0]), np.array([1.0, 0, 0])
    for b0, b1, kind, verts in [
        ([0.5, -1, 0.4], [0.5, 1, 0.4], "ee", lambda: [a0, a1, b0, b1]),  # crossing: line-line
        ([2.0, -1, 0.4], [2.0, 1, 0.4], "pe", lambda: [a1, b0, b1]),  # past a1: a1 to segment b
    ]:
        b0, b1 = np.array(b0), np.array(b1)
        exact = C.edge_edge_distance(a0[None], a1[None], b0[None], b1[None])[0]
        formula = C.pair_distance(kind, np.array(verts()))[0]
        assert exact == pytest.approx(formula, rel=1e-14), (kind, exact, formula)


def test_ccd_returns_t_max_when_the_first_safe_advance_covers_it():
    # A point falling onto a triangle 1 m below, reaching it at t = 0.5: any t_max below the
    # first conservative advance (0.9 of the gap over the closing speed bound) is returned as
    # is, and the pair is indeed apart over [0, t_max].
    tri = np.array([[-1.0, -1, 0], [2, -1, 0], [-1, 2, 0]])
    x0 = np.vstack([[0.1, 0.1, 1.0], tri])
    x1 = np.vstack([[0.1, 0.1, -1.0], tri])
    for t_max in (0.05, 0.2):
        assert C.ccd("pt", x0, x1, t_max) == t_max
        assert sampled_min_distance("pt", x0, x1, t_max) > 0
    assert C.ccd("pt", x0, x1, 1.0) < 0.5
