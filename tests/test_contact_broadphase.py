"""km.contact's kept broad phase: the solver keeps the boxes of static collider primitives
between queries while the collider's vertices stay put, and must see them when they have moved
(a user writing into ``scene.x``) or move along a query's displacement. Its answers must be a
fresh scene's."""

import numpy as np

import kinema as km


def cloth_over_sphere():
    # The cloth 5 mm above the sphere's top, dhat 2 mm: no active pair at the start.
    scene = km.contact.Scene(gravity=(0, -9.81, 0), dhat=2e-3)
    x, tri, springs = km.contact.cloth_mesh(6, 6, 0.5, origin=(-0.25, 0.205, -0.25))
    cloth = scene.add_cloth(x, tri, springs=springs, stiffness=1000, density=0.2)
    scene.add_collider("sphere", center=(0, 0, 0), radius=0.2, subdivisions=2)
    return scene, cloth


def test_kept_broad_phase_sees_a_moved_collider():
    scene, cloth = cloth_over_sphere()
    fresh, _ = cloth_over_sphere()
    sphere = np.ones(len(scene.x), bool)
    sphere[cloth] = False
    assert scene.barrier_energy() == 0  # the trees are built here, at the start
    # The sphere raised by 4 mm: its top 1 mm below the cloth, inside dhat.
    x2 = scene.x.copy()
    x2[sphere, 1] += 4e-3
    e = scene.barrier_energy(x2)
    assert e > 0 and e == fresh.barrier_energy(x2)
    assert scene.barrier_energy() == 0  # and back
    # The sphere swept 1 cm up from the start: it meets the cloth 5 mm on (t < 1/2).
    dx = np.zeros_like(scene.x)
    dx[sphere, 1] = 1e-2
    t = scene.max_safe_step(dx)
    assert 0 < t < 0.5 and t == fresh.max_safe_step(dx)
    # A step still sees the moved sphere: the cloth resting 1 mm above it is pushed, not crossed.
    scene.x[sphere] = x2[sphere]
    st = scene.step(1 / 100)
    assert st.contact_count > 0 and scene.min_distance() > 0 and not scene.intersections()
