"""km.contact's Newton system on a kept pattern: the degrees of freedom only (collider vertices
leave the system), elastic blocks fixed, contact blocks reserved as they appear, the symbolic
analysis reused while the pattern holds. The kept pattern must give the result of the
refactorising solve to rounding, whatever the linear solver; per-collider friction coefficients
(a block on a slope sticks or slides by its collider's coefficient, not the scene's)."""

import numpy as np
import pytest

import kinema as km
from resume import assert_resumes_bitwise

G = 9.81


def cloth_on_sphere(n=6, **options):
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=2e-3, friction=0.3, **options)
    x, tri, springs = km.contact.cloth_mesh(n, n, 0.5, origin=(-0.25, 0.205, -0.25))
    cloth = scene.add_cloth(x, tri, springs=springs, stiffness=1000, density=0.2)
    scene.add_collider("sphere", center=(0, 0, 0), radius=0.2, subdivisions=2)
    return scene, cloth


def cube_pile(**options):
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=1e-3, friction=0.4, **options)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    for k, (dx, dz) in enumerate([(0.0, 0.0), (0.03, -0.02), (-0.02, 0.03)]):
        v, t = km.fem.box_mesh((dx, 0.0015 + 0.105 * k, dz), (dx + 0.1, 0.1015 + 0.105 * k, dz + 0.1), 1)
        scene.add_solid(v, t, youngs_modulus=5e4, poisson_ratio=0.4, density=500)
    return scene


def run(scene, dt, steps):
    history = []
    for _ in range(steps):
        st = scene.step(dt)
        assert scene.min_distance() > 0 and not scene.intersections()
        history.append(st)
    return history


@pytest.mark.parametrize("make,dt,steps", [(lambda **o: cloth_on_sphere(**o)[0], 1 / 50, 12),
                                           (cube_pile, 1 / 100, 25)], ids=["cloth", "pile"])
def test_kept_pattern_matches_the_refactorising_solve(make, dt, steps):
    # Same direct factorisation (CHOLMOD), pattern kept vs. rebuilt and re-analysed at every
    # Newton iteration: the matrices hold the same values (explicit zeros aside), so the
    # iterates agree to rounding: the same Newton iterations per step and positions within
    # a few hundred ulps of the scene size (the orderings differ, so the factors round
    # differently; tol = 1e-2 sits ~12 orders of magnitude above that).
    kept, fresh = make(linear_solver="cholmod"), make(linear_solver="cholmod", reuse_pattern=False)
    hk, hf = run(kept, dt, steps), run(fresh, dt, steps)
    assert [s.newton_iterations for s in hk] == [s.newton_iterations for s in hf]
    assert sum(s.contact_count for s in hk) > 0
    np.testing.assert_allclose(kept.x, fresh.x, rtol=0, atol=1e-11)
    np.testing.assert_allclose(kept.v, fresh.v, rtol=0, atol=1e-11 / dt)
    # The refactorising solve analyses every iteration; the kept pattern only when a contact
    # block first appears (or reserved ones are dropped): far fewer.
    assert [s.pattern_changes for s in hf] == [s.newton_iterations for s in hf]
    changes = sum(s.pattern_changes for s in hk)
    assert 1 <= changes <= sum(s.newton_iterations for s in hk) // 3, changes


def test_collider_vertices_leave_the_system():
    scene, cloth = cloth_on_sphere()
    st = scene.step(1 / 50)
    n_cloth = cloth.stop - cloth.start
    assert len(scene.x) > n_cloth  # the sphere's vertices are in the scene...
    assert st.unknowns == 3 * n_cloth  # ...but not in the Newton system


@pytest.mark.parametrize("solver", ["cholmod", "cholmod-pcg", "cg"])
def test_linear_solvers_agree_with_the_default(solver):
    # Every kind solves the Newton system to rounding (direct) or to a relative residual of
    # 1e-8 (PCG) / 1e-10 (CG); Newton then stops at the same tol, so positions agree within the
    # Newton tolerance's displacement bound tol * diag * dt per step (diag ~ 0.6 m here).
    steps, dt, tol = 10, 1 / 50, 1e-6
    ref, _ = cloth_on_sphere(tol=tol)
    other, _ = cloth_on_sphere(tol=tol, linear_solver=solver)
    run(ref, dt, steps)
    run(other, dt, steps)
    bound = steps * tol * 0.8 * dt
    assert np.abs(ref.x - other.x).max() < bound, (np.abs(ref.x - other.x).max(), bound)
    assert ref.config.linear_solver == "simplicial" and other.config.linear_solver == solver


def test_unknown_linear_solver_is_refused():
    with pytest.raises(ValueError, match="linear_solver"):
        km.contact.Scene(linear_solver="lu")


# ---------------------------------------------------------------- per-collider friction

def slope(theta_deg, scene_mu, plane_mu, steps=30, h=0.01):
    th = np.radians(theta_deg)
    scene = km.contact.Scene(gravity=G * np.array([np.sin(th), -np.cos(th), 0.0]), dhat=1e-3,
                             friction=scene_mu, friction_velocity=1e-4, tol=1e-5)
    v, t = km.fem.box_mesh((0, 5e-4, 0), (0.1, 0.05, 0.1), (2, 1, 2))
    block = scene.add_solid(v, t, youngs_modulus=1e7, poisson_ratio=0.3, density=1000)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0), friction=plane_mu)
    return mean_vx(scene, block, steps, h), h * np.arange(1, steps + 1)


def mean_vx(scene, block, steps, h):
    m = scene.mass[block]
    vx = []
    for _ in range(steps):
        scene.step(h)
        vx.append(m @ scene.v[block, 0] / m.sum())
    return np.array(vx)


def test_plane_friction_overrides_the_scene_coefficient():
    # tan 20 deg = 0.36: the block sticks on a plane of mu = 0.5 in a frictionless scene...
    vx, _ = slope(20.0, 0.0, 0.5)
    assert np.abs(vx[10:]).max() < 1e-4
    # ...and slides with g (sin t - mu cos t) on a plane of mu = 0.2 in a scene of mu = 0.9.
    vx, t = slope(30.0, 0.9, 0.2)
    a = np.polyfit(t[15:], vx[15:], 1)[0]
    expected = G * (np.sin(np.radians(30)) - 0.2 * np.cos(np.radians(30)))
    assert abs(a - expected) < 1e-3 * expected, (a, expected)


def test_mesh_collider_friction_is_its_own():
    # A box collider of mu = 0 under a block in a scene of mu = 1 on a 20 degree slope (gravity
    # tilted): frictionless, the block accelerates at g sin t.
    th = np.radians(20.0)
    scene = km.contact.Scene(gravity=G * np.array([np.sin(th), -np.cos(th), 0.0]), dhat=1e-3, friction=1.0,
                             friction_velocity=1e-4, tol=1e-5)
    v, t = km.fem.box_mesh((0, 5e-4, 0), (0.1, 0.05, 0.1), (2, 1, 2))
    block = scene.add_solid(v, t, youngs_modulus=1e7, poisson_ratio=0.3, density=1000)
    scene.add_collider("box", lower=(-1, -0.1, -1), upper=(3, 0, 1), friction=0.0)
    vx = mean_vx(scene, block, 20, 0.01)
    a = np.polyfit(0.01 * np.arange(10, 20), vx[10:], 1)[0]
    assert abs(a - G * np.sin(th)) < 1e-3 * G * np.sin(th), a


def test_collider_friction_is_checked():
    scene = km.contact.Scene()
    with pytest.raises(ValueError, match="friction"):
        scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0), friction=-0.1)
    with pytest.raises(ValueError, match="friction"):
        scene.add_collider("sphere", radius=1.0, friction=float("nan"))


def test_restored_state_continues_bitwise_after_pattern_changes():
    # The dofs are numbered in a fixed order (AMD of the elastic pattern) and the factorisation
    # runs in that order, so contact blocks reserved by the run before the save (exact zeros
    # in the restored scene's pattern) do not change a bit of what follows.
    stats = assert_resumes_bitwise(cube_pile, lambda s: s.step(0.01), 12, 8)
    assert sum(st.pattern_changes for st in stats) > 1  # body-body contact changed the pattern before the save
