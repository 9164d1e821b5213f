"""What km.contact's solver keeps between Newton iterations and steps: the potential at the
accepted iterate, the active pairs the last step ended with, and broad-phase candidates that
cover several Newton sweeps. All of it must be invisible in the results: a run that resumes from
a saved state (nothing kept: the pairs found again, a broad phase before the first iteration),
or whose state was moved back between steps (kept candidates and pairs stale), continues bit
for bit like the uninterrupted run."""

import numpy as np

import kinema as km
from resume import assert_resumes_bitwise

G = 9.81


def cloth_on_sphere():
    scene = km.contact.Scene(gravity=(0, -G, 0), dhat=2e-3, friction=0.3)
    x, tri, springs = km.contact.cloth_mesh(6, 6, 0.5, origin=(-0.25, 0.205, -0.25))
    scene.add_cloth(x, tri, springs=springs, stiffness=1000, density=0.2)
    scene.add_collider("sphere", center=(0, 0, 0), radius=0.2, subdivisions=2)
    return scene


def test_cloth_resumed_in_a_fresh_scene_continues_bitwise():
    stats = assert_resumes_bitwise(cloth_on_sphere, lambda s: s.step(1 / 50), 10, 8)
    # The saved run was in contact, and its candidates served several Newton sweeps each.
    assert max(st.contact_count for st in stats) > 0
    assert sum(st.broad_phases for st in stats) < sum(st.newton_iterations for st in stats)


def test_state_moved_back_in_the_same_scene_continues_bitwise():
    scene = cloth_on_sphere()
    for _ in range(10):
        scene.step(1 / 50)
    saved = scene.state()
    first = []
    for _ in range(6):
        scene.step(1 / 50)
        first.append(scene.x.copy())
    # Back to the saved state: the step no longer starts where the last one ended, so its pairs
    # and candidates are found again rather than kept.
    scene.set_state(saved)
    for k in range(6):
        st = scene.step(1 / 50)
        assert np.array_equal(scene.x, first[k]), f"step {k}: differs after the state was moved back"
        assert scene.min_distance() > 0 and not scene.intersections()
    assert st.contact_count > 0
