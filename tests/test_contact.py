"""km.contact.Scene: IPC contact between solids, cloth and colliders. Never a penetration
(exact distance and intersection checks after every step), Coulomb friction on a slope against
g (sin t - mu cos t), momentum in a free collision, a resting stack that gains no energy, the
barrier's gradient and Hessian against finite differences on a real mesh, bad input refused."""

import numpy as np
import pytest

import kinema as km
from resume import assert_resumes_bitwise

G = 9.81


def cube(scene, lower, size, n=1, E=1e5, nu=0.3, density=1000.0):
    lo = np.asarray(lower, float)
    v, t = km.fem.box_mesh(lo, lo + size, n)
    return scene.add_solid(v, t, youngs_modulus=E, poisson_ratio=nu, density=density)


def brute_force_min_distance(scene):
    # Every non-adjacent vertex-triangle and edge-edge pair, no broad phase (independent of the
    # BVH the solver uses), with the distance kernels checked against sampling in
    # test_contact_kernels.py.
    C = km._core.contact
    x, F, E = scene.x, scene.faces, scene.edges
    moving = scene.mass > 0
    pts = np.unique(F)
    p, f = np.meshgrid(pts, np.arange(len(F)), indexing="ij")
    p, f = p.ravel(), f.ravel()
    keep = (F[f] != p[:, None]).all(1) & (moving[p] | moving[F[f]].any(1))
    p, f = p[keep], f[keep]
    d_pt = C.point_triangle_distance(x[p], x[F[f, 0]], x[F[f, 1]], x[F[f, 2]])
    a, b = np.triu_indices(len(E), 1)
    keep = (E[a][:, :, None] != E[b][:, None, :]).all((1, 2)) & (moving[E[a]].any(1) | moving[E[b]].any(1))
    a, b = a[keep], b[keep]
    d_ee = C.edge_edge_distance(x[E[a, 0]], x[E[a, 1]], x[E[b, 0]], x[E[b, 1]])
    return np.sqrt(min(d_pt.min(), d_ee.min()))


def assert_separated(scene, step):
    d = scene.min_distance()
    hits = scene.intersections()
    assert d > 0 and not hits, f"step {step}: min distance {d}, intersections {hits}"


# ---------------------------------------------------------------- friction on a slope

def slope_run(theta_deg, mu, steps=40, h=0.01):
    # Tilting gravity instead of the plane: the same physics with an axis-aligned plane.
    th = np.radians(theta_deg)
    scene = km.contact.Scene(gravity=G * np.array([np.sin(th), -np.cos(th), 0.0]), dhat=1e-3,
                             friction=mu, friction_velocity=1e-4, tol=1e-5)
    v, t = km.fem.box_mesh((0, 5e-4, 0), (0.1, 0.05, 0.1), (2, 1, 2))
    block = scene.add_solid(v, t, youngs_modulus=1e7, poisson_ratio=0.3, density=1000)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    m = scene.mass[block]
    vx = []
    for i in range(steps):
        stats = scene.step(h)
        vx.append(m @ scene.v[block, 0] / m.sum())
        assert_separated(scene, i)
    return np.array(vx), h * np.arange(1, steps + 1), stats


def test_block_sticks_below_the_friction_angle():
    vx, _, stats = slope_run(20.0, 0.5)  # tan 20 deg = 0.36 < 0.5
    # The block starts 0.5 mm up, inside dhat: the first steps' friction is lagged from a
    # normal force that is not yet the weight, so it slips a little while it lands. Once
    # landed, static friction holds it to a creep below friction_velocity (1e-4 m/s), as IPC's
    # smoothed Coulomb law allows (without friction it would gain 3.4 cm/s every step).
    assert np.abs(vx[10:]).max() < 1e-4, np.abs(vx[10:]).max()
    assert stats.sticking_count > 0 and stats.sliding_count == 0


@pytest.mark.parametrize("theta,mu", [(30.0, 0.5), (40.0, 0.5), (30.0, 0.2)])
def test_block_slides_above_the_friction_angle_with_coulomb_acceleration(theta, mu):
    vx, t, stats = slope_run(theta, mu)
    a = np.polyfit(t[20:], vx[20:], 1)[0]
    expected = G * (np.sin(np.radians(theta)) - mu * np.cos(np.radians(theta)))
    # Implicit Euler reproduces a constant acceleration exactly; what remains is the Newton
    # tolerance (1e-5 of the size per second in velocity) and the block's elastic settling.
    assert abs(a - expected) < 1e-3 * expected, (a, expected)
    assert stats.sliding_count > 0 and stats.sticking_count == 0


# ---------------------------------------------------------------- conservation

def test_momentum_is_conserved_in_a_free_two_body_collision():
    scene = km.contact.Scene(dhat=1e-3, tol=1e-7)
    a = cube(scene, (0, 0, 0), 0.1)
    b = cube(scene, (0.12, 0.03, 0.02), 0.1)
    scene.v[a] = (1.0, 0.0, 0.0)
    scene.v[b] = (-0.5, 0.1, 0.0)
    p0 = scene.momentum()
    touched = 0
    for i in range(30):
        stats = scene.step(0.005)
        touched += stats.contact_count > 0
        assert_separated(scene, i)
    assert touched > 0
    # Barrier forces come in equal and opposite pairs (every distance is translation
    # invariant), so momentum changes only by the Newton residual: |dx| < tol diag dt per
    # vertex, i.e. |dp| < M tol diag per step.
    diag = np.linalg.norm(scene.x.max(0) - scene.x.min(0))
    bound = 30 * scene.mass.sum() * 1e-7 * diag
    assert np.abs(scene.momentum() - p0).max() < bound, (scene.momentum() - p0, bound)
    # They bounced: the first cube now moves slower along x than it started.
    assert scene.v[a, 0].mean() < 0.9


def test_resting_stack_does_not_gain_energy():
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=1e-3, friction=0.5)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    cube(scene, (0, 5e-4, 0), 0.1, E=1e6)
    cube(scene, (0.01, 0.1 + 1e-3, 0.01), 0.08, E=1e6)
    energies = []
    for i in range(60):
        scene.step(0.01)
        assert_separated(scene, i)
        energies.append(scene.kinetic_energy() + scene.potential_energy())
    energies = np.array(energies)
    # Implicit Euler dissipates: after settling (20 steps) the energy may only go down, up to
    # the Newton tolerance's work m g |dx| <= M g tol diag dt per step.
    tail = energies[20:]
    diag = np.linalg.norm(scene.x.max(0) - scene.x.min(0))
    slack = scene.mass.sum() * G * 1e-2 * diag * 0.01
    assert np.diff(tail).max() <= slack, (np.diff(tail).max(), slack)
    assert scene.kinetic_energy() < 1e-6


# ---------------------------------------------------------------- never a penetration

@pytest.mark.parametrize("seed", [0, 1])
def test_random_drops_never_penetrate(seed):
    rng = np.random.default_rng(seed)
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=1e-3, friction=0.2)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    scene.add_collider("box", lower=(-0.05, 0, -0.05), upper=(0.05, 0.06, 0.05))
    for k in range(3):
        lo = rng.uniform(-0.08, 0.02, 3)
        lo[1] = 0.08 + 0.09 * k
        cube(scene, lo, 0.06, E=3e4)
    scene.v[:] = rng.normal(scale=0.3, size=scene.v.shape) * (scene.mass > 0)[:, None]
    contacts = 0
    for i in range(40):
        stats = scene.step(0.01)
        contacts = max(contacts, stats.contact_count)
        assert_separated(scene, i)
        assert stats.min_distance > 0
        assert brute_force_min_distance(scene) > 0
    assert contacts > 0


def test_cloth_drapes_on_a_sphere_without_penetration():
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=2e-3, friction=0.3)
    x, tri, springs = km.contact.cloth_mesh(8, 8, 0.8, origin=(-0.4, 0.33, -0.4))
    cloth = scene.add_cloth(x, tri, springs=springs, stiffness=1000, density=0.2)
    scene.add_collider("sphere", center=(0, 0, 0), radius=0.3, subdivisions=2)
    for i in range(25):
        stats = scene.step(1 / 50)
        assert_separated(scene, i)
    assert stats.contact_count > 0
    # The middle of the cloth rests on the sphere's top (radius 0.3, faces at most 1.5% inside).
    top = scene.x[cloth][np.argmin(np.linalg.norm(scene.x[cloth][:, [0, 2]], axis=1)), 1]
    assert 0.29 < top < 0.305, top


# ---------------------------------------------------------------- derivatives on a mesh

def test_barrier_gradient_and_hessian_match_finite_differences_on_a_mesh():
    # A generic configuration: the upper cube is turned so that no two edges are parallel
    # (parallel edge-edge pairs switch formula without IPC's mollifier, which is left out).
    scene = km.contact.Scene(dhat=0.02)
    cube(scene, (0, 0, 0), 0.1, n=2)
    v, t = km.fem.box_mesh((-0.05, 0, -0.05), (0.05, 0.1, 0.05), 2)
    a, b = np.radians(30), np.radians(10)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    v = v @ (Rx @ Ry).T
    v += np.array([0.05, 0.1 + 0.01 - v[:, 1].min(), 0.05])  # lowest corner 1 cm above: inside dhat
    scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    x = scene.x.copy()
    assert scene._core.constraint_count(x) > 0
    rng = np.random.default_rng(5)
    g = scene.barrier_gradient(x).ravel()
    H = scene.barrier_hessian(x)
    for _ in range(3):
        u = rng.normal(size=x.shape)
        u /= np.linalg.norm(u)
        eps = 1e-6
        e_p = scene.barrier_energy(x + eps * u)
        e_m = scene.barrier_energy(x - eps * u)
        fd = (e_p - e_m) / (2 * eps)
        # Central differences, eps = 1e-6 against distances of 1 cm: relative truncation
        # (eps / d)^2 ~ 1e-8; asserted to 1e-5 of the gradient's size.
        assert abs(fd - g @ u.ravel()) <= 1e-5 * np.abs(g).sum(), (fd, g @ u.ravel())
        g_p = scene.barrier_gradient(x + eps * u).ravel()
        g_m = scene.barrier_gradient(x - eps * u).ravel()
        Hu = H @ u.ravel()
        err = np.abs((g_p - g_m) / (2 * eps) - Hu).max()
        assert err <= 1e-5 * np.abs(Hu).max(), (err, np.abs(Hu).max())
    # The projected Hessian is positive semidefinite.
    Hp = scene.barrier_hessian(x, project=True).toarray()
    assert np.linalg.eigvalsh(Hp).min() >= -1e-9 * np.abs(Hp).max()


# ---------------------------------------------------------------- state and bad input

def test_state_round_trip_resumes_bitwise():
    def make():
        s = km.contact.Scene(gravity=(0, -G, 0), dhat=1e-3, friction=0.3)
        s.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
        cube(s, (0, 0.01, 0), 0.1)
        return s
    assert_resumes_bitwise(make, lambda s: s.step(0.01), 5, 5)


def test_intersecting_start_is_refused_naming_the_elements():
    scene = km.contact.Scene(dhat=1e-3)
    cube(scene, (0, 0, 0), 0.1)
    cube(scene, (0.051, 0.047, 0.043), 0.1)
    with pytest.raises(ValueError, match=r"intersects.*edge \(\d+, \d+\) crosses triangle"):
        scene.step(0.01)
    touching = km.contact.Scene(dhat=1e-3)
    cube(touching, (0, 0, 0), 0.1)
    cube(touching, (0, 0.1, 0), 0.1)  # resting exactly on the first: distance 0
    with pytest.raises(ValueError, match="touch"):
        touching.step(0.01)
    plane = km.contact.Scene(dhat=1e-3)
    cube(plane, (0, -0.01, 0), 0.1)
    plane.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    with pytest.raises(ValueError, match="behind plane 0"):
        plane.step(0.01)


def test_bad_input_is_refused_clearly():
    with pytest.raises(ValueError, match="friction"):
        km.contact.Scene(friction=-0.1)
    with pytest.raises(ValueError, match="dhat"):
        km.contact.Scene(dhat=0)
    scene = km.contact.Scene()
    v, t = km.fem.box_mesh((0, 0, 0), (1, 1, 1), 1)
    with pytest.raises(ValueError, match="tets: tetrahedron 0 is inverted"):
        scene.add_solid(v, t[:, [1, 0, 2, 3]], youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    with pytest.raises(ValueError, match="tets: index"):
        scene.add_solid(v, t + 100, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    with pytest.raises(ValueError, match="vertices: expected shape"):
        scene.add_solid(v[:, :2], t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    with pytest.raises(ValueError, match="poisson_ratio"):
        scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.5, density=1000)
    with pytest.raises(ValueError, match="shape"):
        scene.add_collider("cylinder")
    with pytest.raises(ValueError, match="radius"):
        scene.add_collider("sphere", center=(0, 0, 0), radius=-1)
    with pytest.raises(ValueError, match="add a body"):
        scene.step(0.01)
    cube(scene, (0, 0, 0), 0.1)
    with pytest.raises(ValueError, match="dt"):
        scene.step(-1.0)
    with pytest.raises(ValueError, match="dt"):
        scene.step(float("nan"))
    with pytest.raises(ValueError, match="dt: .*finite square"):
        scene.step(1e308)
    # A diverged velocity (a step carrying vertices over 1000 scene diagonals) is refused at once
    # and leaves the state as it was (CCD along such a path would crawl for hours).
    x0 = scene.x.copy()
    scene.v = np.full_like(scene.v, 1e300)
    with pytest.raises(km.DivergenceError, match="v: a step of dt"):
        scene.step(0.01)
    np.testing.assert_array_equal(scene.x, x0)


def test_contact_examples_run_small(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "contact_scenes.py"
    spec = importlib.util.spec_from_file_location("contact_scenes", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = module.main(["--out", str(tmp_path), "--small", "--frames", "6"])
    for name in ("cloth", "pile", "stairs"):
        assert (tmp_path / f"contact_{name}.png").stat().st_size > 0
        scene, history = results[name]
        assert len(history) == 6 and all(s.newton_iterations >= 1 for s in history)
