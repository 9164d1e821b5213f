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


# (name, point, expected region); the triangle spans x, z in [0, 1] at y = 0
CASES = {
    "interior (point-plane formula)": (0.25, 0.01, 0.3),
    "near an edge (point-line)": (0.5, 0.008, -0.006),
    "near a corner (point-point)": (-0.007, 0.006, -0.005),
}


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
    # relatively about s / L (gap s ~ 1e-2, edge lengths L ~ 1): within 5 s / L
    s = np.sqrt(d)
    assert diff <= 5 * s * np.linalg.norm(P), (diff / np.linalg.norm(P), s)
    if "point-point" in case:
        # Hess s = (I - n n^T) / s on the pair's difference: orthogonal to grad s, so R = P(H)
        assert diff <= 1e-9 * np.linalg.norm(P), diff


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
