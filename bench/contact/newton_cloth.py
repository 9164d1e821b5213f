"""Cloth on a sphere and a tilted box: kinema's IPC solver (km.contact) beside NVIDIA Newton's
VBD cloth (Vertex Block Descent, Chen et al. 2024, on Warp's CPU device), time per step at equal
step size, in one run.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contact/newton_cloth.py [--sizes 8 12 16] [--steps 40]

Same scene dimensions on both sides (examples/contact_scenes.py's cloth scene): an n x n-cell
square cloth 0.8 m wide at height 0.33 m over a sphere of radius 0.3 m at the origin and a
1.2 x 0.1 x 1.2 m box tilted by 12 degrees about z below it, gravity -9.81 m/s^2 along y,
dt = 1/50 s, cloth density 0.2 kg/m^2. Newton's side: one VBD step per dt with its example's
10 iterations, self-contact on, sphere and box as static collision shapes (analytic, where
kinema uses an icosphere and a box mesh). The models differ (kinema: springs and an IPC
barrier solved to Newton tol 1e-2; VBD: StVK membrane and penalty contact at a fixed iteration
count), so the time per step at equal dt is compared beside each side's accuracy after every
step: kinema's exact minimum distance (cloth to sphere/box meshes and to itself), its count of
penetrations (edges through triangles, exact) and its last Newton step max|dx|/(dt diag) (the
quantity tol bounds); VBD's smallest signed distance of a cloth vertex to the analytic sphere
and box, the number of step-vertex pairs found inside either, and the cloth's
self-intersections (edges through its own triangles, by kinema's exact check on VBD's
triangles). VBD reports no residual (it stops after its fixed iterations).

Warp compiles its CPU kernels on first use: the first steps are run untimed.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import contact_scenes  # noqa: E402
import harness  # noqa: E402

import kinema as km  # noqa: E402

DT = 1 / 50
WIDTH, HEIGHT, RADIUS, TILT = 0.8, 0.33, 0.3, 12.0


def newton_scene(n):
    import newton
    import warp as wp

    wp.set_device("cpu")
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -9.81, 0.0))
    cell = WIDTH / n
    mass = 0.2 * WIDTH * WIDTH / (n + 1) ** 2
    # The grid spans local x, y; a quarter turn about x lays it in the x-z plane at y = HEIGHT.
    builder.add_cloth_grid(pos=wp.vec3(-WIDTH / 2, HEIGHT, -WIDTH / 2),
                           rot=wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), math.pi / 2),
                           vel=wp.vec3(0.0, 0.0, 0.0), dim_x=n, dim_y=n, cell_x=cell, cell_y=cell, mass=mass,
                           tri_ke=1.0e3, tri_ka=1.0e3, tri_kd=1.0e-1, edge_ke=1.0e-2, particle_radius=2e-3)
    builder.add_shape_sphere(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.0), wp.quat_identity()), radius=RADIUS)
    tilt = wp.quat_from_axis_angle(wp.vec3(0.0, 0.0, 1.0), math.radians(TILT))
    builder.add_shape_box(-1, xform=wp.transform(wp.vec3(0.0, -0.45, 0.0), tilt), hx=0.6, hy=0.05, hz=0.6)
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    model.soft_contact_mu = 0.3
    solver = newton.solvers.SolverVBD(model, iterations=10, particle_enable_self_contact=True,
                                      particle_self_contact_margin=2e-3, particle_self_contact_gap=2e-3)
    state0, state1, control = model.state(), model.state(), model.control()
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    states = [state0, state1]

    def step():
        s0, s1 = states
        s0.clear_forces()
        pipeline.collide(s0, contacts)
        solver.step(s0, s1, control, contacts, DT)
        states.reverse()

    def positions():
        return states[0].particle_q.numpy()

    return step, positions, model.tri_indices.numpy()


def box_signed_distance(x):
    # The tilted box of the scene: centre (0, -0.45, 0), half sizes (0.6, 0.05, 0.6), turned
    # by TILT about z. Signed distance of points (negative inside).
    c, s = math.cos(math.radians(TILT)), math.sin(math.radians(TILT))
    p = x - np.array([0.0, -0.45, 0.0])
    local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], 1)  # R^T p
    q = np.abs(local) - np.array([0.6, 0.05, 0.6])
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def run(sizes, steps, out):
    km.set_num_threads(1)
    rec = harness.Recorder(out / "contact_newton.csv", benchmark="contact-newton")
    print(f"commit {harness.git_commit()}  threads 1  dt {DT}")
    summary = []
    for n in sizes:
        scene, dt = contact_scenes.cloth_scene(False, n)
        assert dt == DT
        contacts, cpu, wall = [], {"kinema": 0.0}, []
        min_dist, residual, iterations = [], [], []

        def kinema_run():
            # The exact penetration check runs after each step, outside the step's own times.
            for _ in range(steps):
                c0 = time.process_time()
                st = scene.step(dt)
                cpu["kinema"] += (time.process_time() - c0) / steps
                wall.append(st.seconds)
                contacts.append(st.contact_count)
                iterations.append(st.newton_iterations)
                residual.append(st.newton_history[-1])
                min_dist.append(scene.min_distance())
                assert min_dist[-1] > 0 and not scene.intersections()

        mk = harness.measure(kinema_run, max_tries=1)
        kin_min = min(min_dist)
        kin_residual = max(residual)
        step, positions, tris = newton_scene(n)
        for _ in range(3):  # kernel compilation
            step()
        # VBD's cloth checked by kinema's exact edge-triangle test (a cloth-only scene on VBD's
        # triangles, built from its flat start).
        checker = km.contact.Scene(dhat=1e-6)
        checker.add_cloth(positions(), tris, stiffness=1.0, density=1.0)
        vbd = {"min": np.inf, "inside": 0, "self": 0}

        def newton_run():
            c0 = time.process_time()
            for _ in range(steps):
                step()
            cpu["newton"] = (time.process_time() - c0) / steps

        # Timed without the checks (they run on a second, identical run below).
        mn = harness.measure(newton_run, max_tries=1)
        step, positions, _ = newton_scene(n)
        for _ in range(steps + 3):
            step()
            x = positions()
            assert np.all(np.isfinite(x)), "newton: non-finite positions"
            d = np.minimum(np.linalg.norm(x, axis=1) - RADIUS, box_signed_distance(x))
            vbd["min"] = min(vbd["min"], float(d.min()))
            vbd["inside"] += int(np.sum(d < 0))
            vbd["self"] += len(checker.intersections(x=x, limit=100000))
        size = f"cloth {n}x{n}, {(n + 1) ** 2} cloth vertices, {steps} steps"
        kinema_step = float(np.sum(wall)) / steps
        rec.record("kinema-cloth", size, kinema_step, measurement=mk,
                   notes={"contacts_median": int(np.median(contacts)), "dt": DT, "cpu_ms": f"{cpu['kinema'] * 1e3:.1f}",
                          "min_distance": f"{kin_min:.3g}", "penetrations": 0, "newton_residual": f"{kin_residual:.2g}",
                          "newton_iterations": f"{np.mean(iterations):.1f}"})
        rec.record("newton-vbd-cloth-cpu", size, mn.seconds / steps, measurement=mn,
                   notes={"iterations": 10, "dt": DT, "cpu_ms": f"{cpu['newton'] * 1e3:.1f}",
                          "min_distance": f"{vbd['min']:.3g}", "vertices_inside": vbd["inside"],
                          "self_intersections": vbd["self"]})
        print(f"{size}: kinema {kinema_step * 1e3:8.1f} ms/step (contacts {int(np.median(contacts))}, newton "
              f"{np.mean(iterations):.1f}, load {mk.other_load:.2f})  newton VBD cpu {mn.seconds / steps * 1e3:8.1f} "
              f"ms/step (load {mn.other_load:.2f})  newton/kinema {mn.seconds / steps / kinema_step:5.2f}x | cpu per step "
              f"kinema {cpu['kinema'] * 1e3:.1f} ms, newton {cpu['newton'] * 1e3:.1f} ms, newton/kinema "
              f"{cpu['newton'] / cpu['kinema']:5.2f}x")
        print(f"  accuracy: kinema min distance {kin_min:.3g} m, penetrations 0, last Newton step/(dt diag) <= "
              f"{kin_residual:.2g} (tol {scene.config.tol:g}) | VBD min signed distance to sphere/box {vbd['min']:.3g} m, "
              f"vertices inside a collider {vbd['inside']} (over all steps), cloth self-intersections {vbd['self']}")
        summary.append((n, cpu["newton"] / cpu["kinema"], kin_min, vbd["min"], vbd["inside"], vbd["self"]))
    print("summary (CPU time ratio newton VBD / kinema per step at dt 1/50; >= 2 meets the target): " + ", ".join(
        f"{n}x{n}: {r:.2f}x (min distance kinema {a:.2g} m, VBD {b:.2g} m, VBD inside {c}, self-crossings {d})"
        for n, r, a, b, c, d in summary))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--out", type=Path, default=Path("bench/out"))
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    args.out.mkdir(parents=True, exist_ok=True)
    run(args.sizes, args.steps, args.out)


if __name__ == "__main__":
    main()
