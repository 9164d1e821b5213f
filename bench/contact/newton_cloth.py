"""Cloth on a sphere and a tilted box: kinema's IPC solver (km.contact) beside NVIDIA Newton's
VBD cloth (Vertex Block Descent, Chen et al. 2024, on Warp's CPU device), time per step at equal
step size and at equal measured step accuracy, in one run.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contact/newton_cloth.py [--sizes 8 12 16] [--steps 40]
        [--tols 0.01 0.02 0.03 0.04] [--check-every 2] [--reference-iterations 300] [--quick]

Same scene dimensions on both sides (examples/contact_scenes.py's cloth scene): an n x n-cell
square cloth 0.8 m wide at height 0.33 m over a sphere of radius 0.3 m at the origin and a
1.2 x 0.1 x 1.2 m box tilted by 12 degrees about z below it, gravity -9.81 m/s^2 along y,
dt = 1/50 s, cloth density 0.2 kg/m^2. Newton's side: one VBD step per dt with its example's
10 iterations, self-contact on, sphere and box as static collision shapes (analytic, where
kinema uses an icosphere and a box mesh). The models differ (kinema: springs and an IPC
barrier solved by Newton to `tol`; VBD: StVK membrane and penalty contact at a fixed iteration
count).

Accuracy, both sides alike: every `check_every` steps the step is solved again from the same
state to convergence (VBD with `reference_iterations` iterations; kinema to Newton tol 1e-4)
and the step's error is max |x - x_converged| / (dt diag), diag the scene's bounding-box
diagonal (what kinema's tol bounds through its Newton step). kinema runs once per tolerance in
`tols`; the summary gives the ratio at the default tol 1e-2 and at equal accuracy: the loosest
tol whose median step error is at most VBD's. Also after every step: kinema's exact minimum
distance (cloth to sphere/box meshes and to itself) and penetrations (edges through
triangles, exact); VBD's smallest signed distance of a cloth vertex to the analytic sphere and
box, the vertices found inside either, and the cloth's self-intersections (kinema's exact check
on VBD's triangles).

Warp compiles its CPU kernels on first use: the first steps are run untimed.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import contact_scenes  # noqa: E402
from contact_bench import bench_args  # noqa: E402
import harness  # noqa: E402

import kinema as km  # noqa: E402

DT = 1 / 50
WIDTH, HEIGHT, RADIUS, TILT = 0.8, 0.33, 0.3, 12.0


def newton_scene(n, reference_iterations=None):
    """(step, positions, triangles, step_error) of VBD's cloth scene; step_error() (when
    reference_iterations is given) steps copies of the current state with the run's 10
    iterations and with `reference_iterations` and returns max |x_10 - x_ref| [m], the
    distance of VBD's step from the step's converged solution."""
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
    def vbd(iterations):
        return newton.solvers.SolverVBD(model, iterations=iterations, particle_enable_self_contact=True,
                                        particle_self_contact_margin=2e-3, particle_self_contact_gap=2e-3)

    solver = vbd(10)
    reference = vbd(reference_iterations) if reference_iterations else None
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

    def copy(state):
        out = model.state()
        out.particle_q.assign(state.particle_q)
        out.particle_qd.assign(state.particle_qd)
        return out

    def step_error():
        ends = []
        for run in (solver, reference):
            start, end = copy(states[0]), model.state()
            start.clear_forces()
            pipeline.collide(start, contacts)
            run.step(start, end, control, contacts, DT)
            ends.append(end.particle_q.numpy())
        return float(np.abs(ends[0] - ends[1]).max())

    return step, positions, model.tri_indices.numpy(), step_error


def box_signed_distance(x):
    # The tilted box of the scene: centre (0, -0.45, 0), half sizes (0.6, 0.05, 0.6), turned
    # by TILT about z. Signed distance of points (negative inside).
    c, s = math.cos(math.radians(TILT)), math.sin(math.radians(TILT))
    p = x - np.array([0.0, -0.45, 0.0])
    local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], 1)  # R^T p
    q = np.abs(local) - np.array([0.6, 0.05, 0.6])
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


REFERENCE_TOL = 1e-4


def kinema_scene(n, tol, max_newton=500):
    """The cloth scene with Newton tolerance `tol`."""
    base = km.contact.Scene

    class Scene(base):
        def __init__(self, **kw):
            super().__init__(**{**kw, "tol": tol, "max_newton": max_newton})

    km.contact.Scene = Scene
    try:
        return contact_scenes.cloth_scene(False, n)
    finally:
        km.contact.Scene = base


def step_errors_summary(errors):
    return f"median {np.median(errors):.3g}, max {np.max(errors):.3g}"


def run_kinema(rec, n, steps, tol, check_every):
    """40 steps of kinema at Newton tolerance `tol`: CPU and wall time per step, contacts, Newton
    iterations, exact minimum distance and penetrations after every step, and every
    `check_every` steps the step's error: max |x - x_ref| / (dt diag) against the same step
    re-solved from the same state to REFERENCE_TOL (diag: the scene's bounding-box diagonal;
    Newton's last iterations converge linearly where friction and contacts switch, so a much
    tighter reference would take thousands of iterations)."""
    scene, dt = kinema_scene(n, tol)
    reference, _ = kinema_scene(n, REFERENCE_TOL, 20000)
    assert dt == DT
    diag = float(np.linalg.norm(scene.x.max(axis=0) - scene.x.min(axis=0)))
    out = {"cpu": 0.0, "wall": [], "contacts": [], "iterations": [], "min": [], "errors": [], "diag": diag}

    def kinema_run():
        # The checks run between steps, outside the step's own times.
        for k in range(steps):
            start = scene.state()
            c0 = time.process_time()
            st = scene.step(dt)
            out["cpu"] += (time.process_time() - c0) / steps
            out["wall"].append(st.seconds)
            out["contacts"].append(st.contact_count)
            out["iterations"].append(st.newton_iterations)
            out["min"].append(scene.min_distance())
            assert out["min"][-1] > 0 and not scene.intersections()
            if k % check_every == check_every - 1:
                reference.set_state(start)
                reference.step(dt)
                out["errors"].append(float(np.abs(scene.x - reference.x).max()) / (dt * diag))

    m = harness.measure(kinema_run, max_tries=1)
    size = f"cloth {n}x{n}, {(n + 1) ** 2} cloth vertices, {steps} steps"
    rec.record(f"kinema-cloth-tol{tol:g}", size, float(np.mean(out["wall"])), measurement=m,
               notes={"contacts_median": int(np.median(out["contacts"])), "dt": DT, "tol": tol,
                      "cpu_ms": f"{out['cpu'] * 1e3:.1f}", "min_distance": f"{min(out['min']):.3g}", "penetrations": 0,
                      "step_error_median": f"{np.median(out['errors']):.3g}",
                      "step_error_max": f"{np.max(out['errors']):.3g}",
                      "newton_iterations": f"{np.mean(out['iterations']):.1f}"})
    out["load"] = m.other_load
    return out


def run(sizes, steps, out, tols, check_every, reference_iterations):
    km.set_num_threads(1)
    rec = harness.Recorder(out / "contact_newton.csv", benchmark="contact-newton")
    print(f"commit {harness.git_commit()}  threads 1  dt {DT}")
    summary = []
    for n in sizes:
        kin = {tol: run_kinema(rec, n, steps, tol, check_every) for tol in tols}
        diag = kin[tols[0]]["diag"]
        step, positions, tris, step_error = newton_scene(n, reference_iterations)
        for _ in range(3):  # kernel compilation
            step()
        # VBD's cloth checked by kinema's exact edge-triangle test (a cloth-only scene on VBD's
        # triangles, built from its flat start).
        checker = km.contact.Scene(dhat=1e-6)
        checker.add_cloth(positions(), tris, stiffness=1.0, density=1.0)
        vbd = {"min": np.inf, "inside": 0, "self": 0, "errors": []}
        cpu = {}

        def newton_run():
            c0 = time.process_time()
            for _ in range(steps):
                step()
            cpu["newton"] = (time.process_time() - c0) / steps

        # Timed without the checks (they run on a second, identical run below).
        mn = harness.measure(newton_run, max_tries=1)
        step, positions, _, step_error = newton_scene(n, reference_iterations)
        for _ in range(3):
            step()
        for k in range(steps):
            if k % check_every == check_every - 1:
                vbd["errors"].append(step_error() / (DT * diag))
            step()
            x = positions()
            assert np.all(np.isfinite(x)), "newton: non-finite positions"
            d = np.minimum(np.linalg.norm(x, axis=1) - RADIUS, box_signed_distance(x))
            vbd["min"] = min(vbd["min"], float(d.min()))
            vbd["inside"] += int(np.sum(d < 0))
            vbd["self"] += len(checker.intersections(x=x, limit=100000))
        size = f"cloth {n}x{n}, {(n + 1) ** 2} cloth vertices, {steps} steps"
        rec.record("newton-vbd-cloth-cpu", size, mn.seconds / steps, measurement=mn,
                   notes={"iterations": 10, "dt": DT, "cpu_ms": f"{cpu['newton'] * 1e3:.1f}",
                          "min_distance": f"{vbd['min']:.3g}", "vertices_inside": vbd["inside"],
                          "self_intersections": vbd["self"],
                          "step_error_median": f"{np.median(vbd['errors']):.3g}",
                          "step_error_max": f"{np.max(vbd['errors']):.3g}",
                          "reference_iterations": reference_iterations})
        print(f"{size}: newton VBD cpu {cpu['newton'] * 1e3:6.1f} ms/step (wall {mn.seconds / steps * 1e3:.1f}, load "
              f"{mn.other_load:.2f}); step error / (dt diag) {step_errors_summary(vbd['errors'])} (against "
              f"{reference_iterations} iterations); min signed distance to sphere/box {vbd['min']:.3g} m, vertices "
              f"inside a collider {vbd['inside']} (over all steps), cloth self-intersections {vbd['self']}")
        for tol, k in kin.items():
            print(f"  kinema tol {tol:<6g} cpu {k['cpu'] * 1e3:6.1f} ms/step (wall {np.mean(k['wall']) * 1e3:.1f}, load "
                  f"{k['load']:.2f}), newton {np.mean(k['iterations']):4.1f}, contacts {int(np.median(k['contacts']))}; "
                  f"step error / (dt diag) {step_errors_summary(k['errors'])}; min distance {min(k['min']):.3g} m, "
                  f"penetrations 0; VBD / kinema cpu {cpu['newton'] / k['cpu']:5.2f}x")
        # Equal accuracy: the loosest tolerance whose median step error is at most VBD's.
        vbd_err = float(np.median(vbd["errors"]))
        fair = [t for t in tols if np.median(kin[t]["errors"]) <= vbd_err]
        fair_tol = max(fair) if fair else None
        at = kin[fair_tol] if fair_tol else None
        summary.append((n, cpu["newton"] / kin[tols[0]]["cpu"], tols[0], fair_tol,
                        cpu["newton"] / at["cpu"] if at else float("nan"), vbd_err,
                        float(np.median(at["errors"])) if at else float("nan"), cpu["newton"] * 1e3,
                        at["cpu"] * 1e3 if at else float("nan"), float(np.mean(at["iterations"])) if at else float("nan")))
    print(f"summary (commit {harness.git_commit()}, kinema {km.__file__}; CPU time ratio newton VBD / kinema per step "
          "at dt 1/50; >= 2 meets the target): " + "; ".join(
              f"{n}x{n}: {r:.2f}x at tol {t0:g}, {rf:.2f}x at equal accuracy (tol {tf}: kinema {km_ms:.1f} ms, "
              f"{its:.2f} Newton iterations, median step error {ek:.3g} <= VBD's {ev:.3g} at {vbd_ms:.1f} ms)"
              for n, r, t0, tf, rf, ev, ek, vbd_ms, km_ms, its in summary))


def main(argv=None):
    def options(parser):
        parser.add_argument("--sizes", type=int, nargs="+", default=[8, 12, 16])
        parser.add_argument("--steps", type=int, default=40)
        parser.add_argument("--tols", type=float, nargs="+", default=[1e-2, 2e-2, 3e-2, 4e-2],
                            help="kinema's Newton tolerances (the first is the default 1e-2)")
        parser.add_argument("--check-every", type=int, default=2, help="steps between step-error checks")
        parser.add_argument("--reference-iterations", type=int, default=300,
                            help="VBD iterations of the converged reference step")

    args = bench_args(__doc__, argv, options)
    sizes = [8, 12] if args.quick else args.sizes
    run(sizes, args.steps, args.out, args.tols, args.check_every, args.reference_iterations)


if __name__ == "__main__":
    main()
