"""The rank-one (Gauss-Newton) barrier Hessian the solver assembles by default, against the
eigen clamp of the exact Hessian (barrier.h). With d = s^2 the squared distance of a pair,
    H = alpha grad s grad s^T + beta Hess s,   alpha = 4 d b'' + 2 b',  beta = 2 s b',
and R = max(alpha, 0) grad s grad s^T is the PSD projection P of the first term; P is
1-Lipschitz in the Frobenius norm, so |P(H) - R|_F <= |H - alpha grad s grad s^T|_F = |beta| |Hess s|_F,
which is small against |P(H)| when the gap is small against the edge lengths (about s / L).
Checked on a single point-triangle pair (so the scene's matrices are the pair's) in each
closest-point region, with grad s taken from the exact gradient: R's formula, the bound, its
relative size, and R = P(H) exactly where Hess s is orthogonal to grad s (vertex-vertex pairs
and vertex-plane pairs)."""

import numpy as np
import pytest

import kinema as km

C = km._core.contact
DHAT = 0.02


def clamp(H):
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    return (V * np.maximum(w, 0)) @ V.T


def pair_scene(point):
    """A unit-sized triangle (cloth) and one free point (a mass-spring body without springs)."""
    scene = km.contact.Scene(dhat=DHAT)
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    scene.add_cloth(tri, np.array([[0, 1, 2]]), springs=np.zeros((0, 2), np.int64), stiffness=1.0, density=1.0)
    body = km.massspring.System(np.asarray(point, float)[None, :], np.zeros((0, 2), np.int64), stiffness=1.0, mass=1.0)
    scene.add_body(body)
    return scene


def matrices(scene):
    x = scene.x.copy()
    d = scene.min_distance(x=x, radius=DHAT) ** 2
    _, b1, b2 = C.barrier(d, DHAT**2)
    g = scene.barrier_gradient(x).ravel()  # b' grad d
    H = scene.barrier_hessian(x, project="none").toarray()
    R = scene.barrier_hessian(x, project="rank-one").toarray()
    P = scene.barrier_hessian(x, project="clamp").toarray()
    grad_s = g / b1 / (2 * np.sqrt(d))
    alpha = 4 * d * b2 + 2 * b1
    return d, alpha, grad_s, H, R, P


# (name, point); the triangle spans x, z in [0, 1] at y = 0; the point is closest to its interior,
# to its edge x0 x1 (z = 0), or to its corner x0
CASES = {
    "interior (point-plane formula)": (0.25, 0.01, 0.3),
    "near an edge (point-line)": (0.5, 0.008, -0.006),
    "near a corner (point-point)": (-0.007, 0.006, -0.005),
}


def distance(y, case):
    """The pair's distance s in its region, written out independently of kinema (y: the scene's
    four vertices, the triangle's x0 x1 x2 then the point p)."""
    x0, x1, x2, p = y
    if "interior" in case:
        n = np.cross(x1 - x0, x2 - x0)
        return abs((p - x0) @ n) / np.linalg.norm(n)
    if "edge" in case:
        t = x1 - x0
        return np.linalg.norm(np.cross(p - x0, t)) / np.linalg.norm(t)
    return np.linalg.norm(p - x0)


def curvature_split(x, case, grad_s):
    """|B|_F where Hess s = A / s + B: A / s the part curving with 1 / s around the closest
    feature (none for the plane; (I - n n^T - t t^T) / s on the difference p - c for the line,
    c the closest point at edge parameter lam; (I - n n^T) / s on p - x0 for the point), PSD and
    orthogonal to grad s; B the rest, from the turning of the feature (of size 1 / L).
    Hess s by central differences of `distance` with step eta = 1e-5: truncation per entry
    eta^2 / 3 |D^4 s| <= eta^2 / 3 * 15 / s^3 = 5e-4 (s = 1e-2), so <= 12 * 5e-4 = 6e-3 in the
    Frobenius norm of the 12 x 12 matrix; rounding 1e-16 s / eta^2 = 1e-8."""
    y, eta, m = x.reshape(4, 3).copy(), 1e-5, 12
    hess = np.zeros((m, m))
    for i in range(m):
        for j in range(m):
            val = 0.0
            for si, sj, w in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
                z = y.ravel().copy()
                z[i] += si * eta
                z[j] += sj * eta
                val += w * distance(z.reshape(4, 3), case)
            hess[i, j] = val / (4 * eta**2)
    x0, x1, _, p = y
    s = distance(y, case)
    n = grad_s[9:] / np.linalg.norm(grad_s[9:])  # grad_p s = n
    if "interior" in case:
        return np.linalg.norm(hess)
    if "edge" in case:
        t = (x1 - x0) / np.linalg.norm(x1 - x0)
        lam = (p - x0) @ t / np.linalg.norm(x1 - x0)
        J = np.hstack([-(1 - lam) * np.eye(3), -lam * np.eye(3), np.zeros((3, 3)), np.eye(3)])
        A = J.T @ (np.eye(3) - np.outer(n, n) - np.outer(t, t)) @ J
    else:
        J = np.hstack([-np.eye(3), np.zeros((3, 6)), np.eye(3)])
        A = J.T @ (np.eye(3) - np.outer(n, n)) @ J
    return np.linalg.norm(hess - A / s)


@pytest.mark.parametrize("case", sorted(CASES))
def test_rank_one_hessian_is_the_clamped_normal_term_within_the_lipschitz_bound(case):
    scene = pair_scene(CASES[case])
    assert scene._core.constraint_count(scene.x) == 1
    d, alpha, grad_s, H, R, P = matrices(scene)
    scale = np.abs(P).max()
    # the formula: R = max(alpha, 0) grad s grad s^T, PSD
    assert np.abs(R - max(alpha, 0) * np.outer(grad_s, grad_s)).max() <= 1e-10 * scale
    assert np.linalg.eigvalsh(R).min() >= -1e-12 * scale
    # |P(H) - R|_F <= |H - alpha grad s grad s^T|_F (rounding of the eigen solve aside)
    bound = np.linalg.norm(H - alpha * np.outer(grad_s, grad_s))
    diff = np.linalg.norm(P - R)
    assert diff <= bound * (1 + 1e-9) + 1e-12 * np.linalg.norm(P), (diff, bound)
    # Sharper, and why it is small (about s / L): with Hess s = A / s + B as in curvature_split,
    # beta A / s = 2 b' A is negative semidefinite (b' < 0) and orthogonal to grad s, so
    # P(alpha grad s grad s^T + beta A / s) = R exactly, and the 1-Lipschitz P gives
    #     |P(H) - R|_F <= |beta| |B|_F,  i.e.  |P(H) - R|_F / |R|_F <= s (2 |b'| / alpha) |B|_F / |grad s|^2,
    # with |B|_F ~ 1 / L (B = 0 for the point: R = P(H) there). Added: B's central-difference
    # error (6e-3 at most, curvature_split; 1e-2 taken) and the eigen solve's rounding (1e-12 |P|).
    s = np.sqrt(d)
    x = scene.x.ravel()
    np.testing.assert_allclose(distance(x.reshape(4, 3), case), s, rtol=1e-12)
    B = curvature_split(x, case, grad_s)
    _, b1, _ = C.barrier(d, DHAT**2)
    assert b1 < 0 < alpha
    assert diff <= abs(2 * s * b1) * (B + 1e-2) + 1e-12 * np.linalg.norm(P), (diff, abs(2 * s * b1) * B, B)
    if "point-point" in case:
        assert B <= 1e-2, B  # central-difference error only: B = 0


def test_rank_one_hessian_equals_the_clamp_for_vertex_plane_contacts():
    scene = km.contact.Scene(dhat=1e-3)
    v, t = km.fem.box_mesh((0, 4e-4, 0), (0.1, 0.1004, 0.1), 2)
    scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0.1, 1, 0.05))
    x = scene.x
    assert scene._core.constraint_count(x) > 0
    R = scene.barrier_hessian(x, project="rank-one").toarray()
    P = scene.barrier_hessian(x, project="clamp").toarray()
    assert np.abs(R - P).max() <= 1e-12 * np.abs(P).max()


def test_projection_options_are_checked():
    with pytest.raises(ValueError, match="barrier_projection"):
        km.contact.Scene(barrier_projection="eigen")
    scene = pair_scene((0.25, 0.01, 0.3))
    with pytest.raises(ValueError, match="project"):
        scene.barrier_hessian(project="abs")
    assert km.contact.Scene().config.barrier_projection == "rank-one"
    assert km.contact.Scene(barrier_projection="clamp").config.barrier_projection == "clamp"
