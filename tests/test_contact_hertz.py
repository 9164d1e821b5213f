"""Hertzian contact (Johnson, Contact Mechanics, 1985, sec. 4.2): a soft neo-Hookean ball of
radius R resting on a rigid plane under its weight F has a circular contact of radius
a = (3 F R / (4 E*))^(1/3), E* = E / (1 - nu^2). Measured (n = 16): contact force 5.11223 N
against the weight 5.11215 N; outermost vertex in contact at r = 12.42 mm against a = 12.04 mm
(the bound below is h + band = 7.4 mm: at this resolution the contact is 2 grid spacings
wide)."""

import numpy as np
import pytest

import kinema as km


def ball_mesh(radius, n):
    """Tetrahedra of a ball: km.fem.box_mesh of [-1, 1]^3 (n cells per axis) pushed radially
    onto the ball (x |x|_inf / |x|_2). Surface vertices lie on the sphere; near the poles the
    surface vertices form a grid of spacing about 2 radius / n."""
    V, T = km.fem.box_mesh((-1, -1, -1), (1, 1, 1), n)
    inf, l2 = np.abs(V).max(axis=1), np.linalg.norm(V, axis=1)
    scale = np.where(l2 > 0, inf / np.where(l2 > 0, l2, 1), 1)
    return radius * V * scale[:, None], T


@pytest.mark.slow
def test_ball_on_a_plane_matches_hertz():
    R, E, nu, rho, g = 0.05, 1e5, 0.3, 1000.0, 9.81
    n = 16
    V, T = ball_mesh(R, n)
    assert km.mesh.signed_volumes(V, T).min() > 0
    V[:, 1] += R + 1e-6  # resting just above the plane
    dhat = 1e-5
    scene = km.contact.Scene(gravity=(0, -g, 0), dhat=dhat, tol=1e-4)
    rows = scene.add_solid(V, T, youngs_modulus=E, poisson_ratio=nu, density=rho, damping=5.0)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    dt = 0.5
    for _ in range(8):  # large implicit steps with damping: a quasi-static solve
        stats = scene.step(dt)
    assert np.abs(scene.v).max() < 1e-4, np.abs(scene.v).max()
    x = scene.x[rows]
    F = scene.mass[rows].sum() * g
    # Contact force of the barrier on every vertex: -(kappa / dt^2) grad B (kappa carries dt^2).
    f = -(stats.barrier_stiffness / dt**2) * scene.barrier_gradient()[rows]
    # Equilibrium: the contact force carries the weight (to the Newton tolerance).
    assert f[:, 1].sum() == pytest.approx(F, rel=1e-3)
    E_star = E / (1 - nu**2)
    a_hertz = (3 * F * R / (4 * E_star)) ** (1 / 3)
    r = np.hypot(x[:, 0], x[:, 2])
    touching = f[:, 1] > 1e-9 * F
    a_nodes = r[touching].max()
    # Resolution: the discrete contact edge lies between the outermost vertex in contact and
    # the next surface vertex outward, one grid spacing h = 2 R / n further; the barrier band
    # (vertices within dhat of the plane) widens it by about (dhat R / a)^(2/3) (the gap
    # outside a Hertz contact grows as (r - a)^(3/2) a / R). So |a_nodes - a| <= h + that band.
    h = 2 * R / n
    band = (dhat * R / a_hertz) ** (2 / 3)
    assert abs(a_nodes - a_hertz) <= h + band, (a_nodes, a_hertz, h, band)
