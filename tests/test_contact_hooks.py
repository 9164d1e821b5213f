"""Contact for km.fem and km.massspring users: colliders on a body (implicit steps by IPC,
symplectic steps by projection), moving colliders, several bodies in one scene."""

import numpy as np
import pytest

import kinema as km
from scene_toml import cloth, fem_box

G = (0.0, -9.81, 0.0)


def cube(lower=(0, 0.05, 0), size=0.1, n=2):
    return km.fem.box_mesh(lower, tuple(np.add(lower, size)), n)


def test_fem_body_rests_on_a_plane_collider_implicit():
    V, T = cube()
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000, gravity=G, damping=1.0)
    body.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    for _ in range(60):
        stats = body.step(1e-2)
        # never through the plane: every vertex strictly above it at every step
        assert body.x[:, 1].min() > 0, body.x[:, 1].min()
    assert stats.contact_count > 0 and 0 < stats.min_distance < body.contact.scene().config.dhat
    assert body.time == pytest.approx(0.6)
    # at rest on the plane: the weight is carried (speeds small against the free-fall speed g t)
    assert np.abs(body.v).max() < 0.05 * 9.81 * 0.6, np.abs(body.v).max()


def test_cloth_on_a_sphere_with_a_moving_box_is_intersection_free():
    c = km.massspring.cloth(8, 8, 0.5, plane="xz", origin=(-0.25, 0.25, -0.25))
    cloth = km.massspring.System(c.x, c.springs, stiffness=500.0, mass=0.01, gravity=G, damping=0.01)
    km.contact.attach(cloth, triangles=c.triangles, friction=0.3, dhat=1e-3)
    cloth.add_collider("sphere", center=(0, 0, 0), radius=0.2, subdivisions=2)
    cloth.add_collider("box", lower=(-1, -0.5, -1), upper=(1, -0.3, 1), velocity=(0, 0.5, 0))
    scene = cloth.contact.scene()
    for _ in range(30):
        stats = cloth.step(1e-2)
        assert scene.min_distance(radius=1.0) > 0
        assert not scene.intersections()
    # the box followed its script exactly (vertices at their scripted place)
    np.testing.assert_allclose(scene.x[scene.colliders[1]["rows"]], scene.collider_positions(1), atol=1e-12)
    assert stats.sticking_count + stats.sliding_count > 0
    np.testing.assert_array_equal(cloth.x, scene.x[: len(cloth.x)])


def test_moving_box_pushes_a_body_and_nothing_passes_through():
    V, T = cube((0, 0.001, 0), 0.1, 2)
    scene = km.fem.Scene(dhat=1e-3)
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    rows = scene.add_body(body)
    # a wall moving along +x at 1 m/s from x = -0.05 into the body
    scene.add_collider("box", lower=(-0.1, -0.05, -0.05), upper=(-0.05, 0.15, 0.15), velocity=(1.0, 0, 0))
    for _ in range(15):
        scene.step(1e-2)
        assert scene.min_distance(radius=1.0) > 0 and not scene.intersections()
    wall = scene.collider_positions(0)
    # the wall is at its scripted place and the body was pushed ahead of it
    assert wall[:, 0].max() == pytest.approx(-0.05 + 0.15)
    assert body.x[:, 0].min() > wall[:, 0].max()
    assert body.v[:, 0].mean() > 0.9  # carried along at the wall speed or faster (elastic rebound)
    np.testing.assert_array_equal(body.x, scene.x[rows])


def test_two_fem_bodies_and_a_cloth_in_one_scene():
    scene = km.fem.Scene(gravity=G, dhat=5e-4)
    V, T = cube((0, 0.01, 0), 0.1, 2)
    a = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=500, gravity=G)
    V2, T2 = cube((0.0, 0.15, 0.0), 0.1, 2)
    b = km.fem.Body(V2, T2, youngs_modulus=2e5, poisson_ratio=0.3, density=500, gravity=G)
    c = km.massspring.cloth(6, 6, 0.3, plane="xz", origin=(-0.1, 0.3, -0.1))
    cloth = km.massspring.System(c.x, c.springs, stiffness=200.0, mass=0.005, gravity=G)
    scene.add_body(a)
    scene.add_body(b)
    scene.add_body(cloth, triangles=c.triangles)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    for _ in range(20):
        scene.step(1e-2)
        assert scene.min_distance(radius=1.0) > 0
    assert a.x[:, 1].min() > 0
    # b rests on a. No penetration is min_distance's check above; comparing b's lowest vertex with
    # a's highest is not (during the impact the faces bulge by ~2e-4 m, more than the barrier's
    # gap, while staying apart). b's centre lies above a's top face and inside a's footprint.
    centre = b.x.mean(axis=0)
    assert centre[1] > a.x[:, 1].max()
    assert np.all(centre[[0, 2]] > a.x[:, [0, 2]].min(axis=0))
    assert np.all(centre[[0, 2]] < a.x[:, [0, 2]].max(axis=0))
    with pytest.raises(ValueError, match="gravity"):
        scene.add_body(km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=500))


@pytest.mark.parametrize("dim", [2, 3])
def test_symplectic_projection_never_gains_energy_and_keeps_out(dim):
    if dim == 3:
        V, T = cube((0, 0.02, 0), 0.1, 2)
    else:
        V, T = km.fem.rectangle_mesh((0, 0.02), (0.1, 0.12), 4)
    g = G if dim == 3 else G[:2]
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000, gravity=g)
    body.add_collider("plane", point=np.zeros(dim), normal=np.eye(dim)[1], friction=0.5)
    body.add_collider("sphere", center=np.r_[0.3, np.zeros(dim - 1)], radius=0.05)
    dt = 0.5 * body.explicit_dt_limit
    e0 = body.energy()
    energies, projected = [], 0
    for _ in range(int(0.4 / dt)):
        stats = body.step(dt, "symplectic")
        projected += stats.contact_count
        assert body.x[:, 1].min() >= -1e-15
        energies.append(body.energy())
    assert projected > 0
    # In free fall symplectic Euler's energy after k steps is E0 - k m g^2 dt^2 / 2 (never
    # above E0); the inelastic projection only removes energy. Allow one step's gravitational
    # energy error m g^2 dt^2 for the elastic exchange after the impact.
    bound = body.mass.sum() * 9.81 ** 2 * dt ** 2
    assert max(energies) <= e0 + bound, (max(energies), e0, bound)
    assert energies[-1] < 0.9 * e0  # the impact dissipated (inelastic projection)


def test_symplectic_tunnelling_limit_is_checked():
    V, T = cube((0, 0.3, 0), 0.1, 1)
    body = km.fem.Body(V, T, youngs_modulus=1e4, poisson_ratio=0.3, density=1000, gravity=G)
    body.v[:, 1] = -50.0
    body.add_collider("box", lower=(-1, 0.0, -1), upper=(1, 0.02, 1))  # 2 cm thick
    with pytest.raises(ValueError, match="dt: .* pass through"):
        body.step(1e-3, "symplectic")  # 5 cm a step through 2 cm of box


def test_bad_collider_options_are_refused():
    V, T = cube()
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    with pytest.raises(ValueError, match="friction"):
        body.add_collider("plane", friction=-1)
    with pytest.raises(ValueError, match="angular_velocity: a plane collider moves by translation only"):
        body.add_collider("plane", angular_velocity=(1, 0, 0))
    V2, T2 = km.fem.rectangle_mesh((0, 0), (1, 1), 2)
    flat = km.fem.Body(V2, T2, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    flat.add_collider("plane", point=(0, -1), normal=(0, 1))
    with pytest.raises(ValueError, match="3D only"):
        flat.step(1e-2)
    msys = km.massspring.System(np.eye(3), [[0, 1]], stiffness=1.0)
    msys.add_collider("plane", point=(0, -1, 0))
    with pytest.raises(ValueError, match="beta"):
        msys.step(1e-2, beta=0.5)


def test_a_body_with_colliders_is_refused_by_km_diff():
    V, T = cube()
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000, gravity=G)
    body.add_collider("plane", point=(0, 0, 0))
    with pytest.raises(ValueError, match="not differentiable"):
        km.diff.rollout(body, 2, 1e-2, wrt=("x",))


def test_attach_options_are_set_once():
    V, T = cube()
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000, gravity=G)
    km.contact.attach(body, friction=0.3, dhat=2e-4)
    body.add_collider("plane", point=(0, 0, 0))
    assert km.contact.attach(body) is body.contact  # no options: the same object
    with pytest.raises(ValueError, match="friction: the contact options of this body are already set"):
        km.contact.attach(body, friction=0.5)
    body.step(1e-2)
    assert body.contact.scene().config.dhat == 2e-4 and body.contact.scene().config.friction == 0.3


SCENE = """
[scene]
name = "t"
duration = 0.04
fps = 50

[solver]
type = "{solver}"
gravity = [0.0, -9.81, 0.0]
friction = 0.2
dhat = 1e-3

{body}

[[objects]]
type = "collider"
shape = "mesh"
file = "bowl.obj"

[[objects]]
type = "obstacle"
shape = "box"
lower = [-0.3, 0.5, -0.3]
upper = [0.3, 0.6, 0.3]
velocity = [0.0, 0.5, 0.0]

[output]
png = false
mp4 = false
vtu = false
ply = false
"""
BODIES = {
    "fem": "\n\n".join("[[objects]]\n" + fem_box(lower, upper, youngs_modulus=1e5, density=500.0)
                       for lower, upper in [((0.0, 0.05, 0.0), (0.1, 0.15, 0.1)), ((0.0, 0.2, 0.0), (0.1, 0.3, 0.1))]),
    "massspring": "[[objects]]\n" + cloth((4, 4), (0.3, 0.3), (-0.1, 0.2, -0.1), stiffness=200.0, mass=0.05),
}


@pytest.mark.parametrize("solver", ["fem", "massspring"])
def test_scene_files_take_mesh_and_moving_colliders(tmp_path, solver):
    import meshio

    v, t = km.contact.box_surface((-0.5, -0.1, -0.5), (0.5, 0.0, 0.5))
    meshio.write(tmp_path / "bowl.obj", meshio.Mesh(v, [("triangle", t)]))
    path = tmp_path / "scene.toml"
    path.write_text(SCENE.format(solver=solver, body=BODIES[solver]))
    scene = km.Scene.load(path)
    result = scene.run(tmp_path / "out", 3, progress=False)
    assert result.frames == 3
    with open(tmp_path / "out" / "diagnostics.csv") as fh:
        header = fh.readline()
    assert "min_distance" in header and "contact_count" in header
    bad = path.read_text().replace('file = "bowl.obj"', "")
    path.write_text(bad)
    with pytest.raises(ValueError, match="file"):
        km.Scene.load(path).build()


def test_a_single_vertex_lands_on_a_plane():
    """A scene whose bodies span nothing (one mass point, no springs) steps like any other: it
    falls freely (y = y0 - g t^2/2 ... the implicit Euler path) and then rests above the plane."""
    point = km.massspring.System(np.array([[0.0, 0.05, 0.0]]), np.zeros((0, 2), dtype=np.int64),
                                 stiffness=1.0, mass=0.01, gravity=G)
    point.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    y = [0.05]
    for _ in range(40):
        point.step(5e-3)
        y.append(point.x[0, 1])
        assert point.x[0, 1] > 0
    # before touching anything: implicit Euler's free fall, y_k = y0 - g h^2 k(k+1)/2
    k = np.arange(1, 6)
    assert np.allclose(y[1:6], 0.05 - 9.81 * 5e-3 ** 2 * k * (k + 1) / 2, rtol=0, atol=1e-12)
    assert 0 < y[-1] < 1e-2 and abs(point.v[0, 1]) < 0.05
