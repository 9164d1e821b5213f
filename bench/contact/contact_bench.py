"""km.contact benchmarks: time per step against contact count (the cube pile and the cloth on a sphere of examples/contact_scenes.py) with
Newton iterations and the CCD's share, and the contact kernels side by side with the IPC
toolkit's Python bindings (``ipctk``, the ``bench`` extra) on the same meshes and positions.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contact/contact_bench.py [--quick] [--out bench/out]
        [--variants simplicial cholmod cholmod-refactorise cholmod-pcg] [--no-kernels]

The per-step sweep runs each scene with each linear-solver variant of the Newton system (the
kept pattern with Eigen's simplicial Cholesky, the default; the kept pattern with CHOLMOD; CHOLMOD
re-analysed whenever the contact pattern changes, the former solver; PCG preconditioned by a
lagged CHOLMOD factor) and prints a summary line of CPU ms per step.

Kernels compared (both sides single-threaded, both from Python with one call per mesh):

* barrier: build the active set (pairs closer than dhat) and evaluate the barrier energy;
* gradient / hessian: the same plus the barrier gradient / (per-contact PSD-projected) Hessian;
* ccd: the largest intersection-free step size along a displacement (kinema: additive CCD;
  ipctk: its default Tight-Inclusion CCD and its additive CCD).

Before a time is recorded each result is checked: kinema's barrier gradient against central
differences of its energy along a random direction, and both step sizes by an exact
intersection check of kinema's at the returned step. The barrier conventions differ (ipctk
1.x evaluates its barrier on distances, kinema on squared distances as in Li et al. 2020), so
values are not compared with each other; the active sets are counted on both sides.
"""

from __future__ import annotations

import argparse
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


# Linear-solver variants of the Newton system (km.contact.Scene options): the kept pattern with
# Eigen's simplicial Cholesky (the default), the kept pattern with CHOLMOD's supernodal one,
# CHOLMOD re-analysed whenever the contact pattern changes (the former solver), and PCG
# preconditioned by a lagged CHOLMOD factor on the kept pattern.
VARIANTS = {
    "simplicial": dict(linear_solver="simplicial"),
    "cholmod": dict(linear_solver="cholmod"),
    "cholmod-refactorise": dict(linear_solver="cholmod", reuse_pattern=False),
    "cholmod-pcg": dict(linear_solver="cholmod-pcg"),
}


def with_options(make, options):
    """The scene `make` builds, with Scene keyword options replaced."""
    base = km.contact.Scene

    class Scene(base):
        def __init__(self, **kw):
            super().__init__(**{**kw, **options})

    km.contact.Scene = Scene
    try:
        return make()
    finally:
        km.contact.Scene = base


def pile(count, n):
    return contact_scenes.pile_scene(False, count, n)


def cloth(n):
    return contact_scenes.cloth_scene(False, n)


def solver_sweep(rec, quick, variants):
    cases = [("pile", lambda c=c, n=n: pile(c, n), f"{c} cubes n={n}") for c, n in ((2, 2), (4, 2), (4, 3))]
    cases += [("cloth", lambda n=n: cloth(n), f"cloth {n}x{n}") for n in ((8, 12) if quick else (8, 12, 16))]
    steps = 15 if quick else 40
    summary = {}
    for name, make, label in cases:
        for variant in variants:
            scene, dt = with_options(make, VARIANTS[variant])
            rows = []
            cpu = []

            def run():
                for _ in range(steps):
                    c0 = time.process_time()
                    st = scene.step(dt)
                    cpu.append(time.process_time() - c0)
                    rows.append((st.seconds, st.contact_count, st.newton_iterations, st.ccd_share, st.pattern_changes,
                                 st.solve_seconds / max(st.seconds, 1e-30)))
                    assert scene.min_distance() > 0 and not scene.intersections()

            # One timed run (a simulation cannot be repeated from the same state without a
            # reset); the machine's load during it is recorded with the figure.
            m = harness.measure(run, max_tries=1)
            contact_rows = [r for r in rows if r[1] > 0] or rows
            sec = np.median([r[0] for r in contact_rows])
            contacts = int(np.median([r[1] for r in contact_rows]))
            newton = float(np.mean([r[2] for r in contact_rows]))
            ccd = float(np.mean([r[3] for r in contact_rows]))
            solve = float(np.mean([r[5] for r in contact_rows]))
            analyses = sum(r[4] for r in rows) / max(1, sum(r[2] for r in rows))
            cpu_ms = 1e3 * float(np.median([c for c, r in zip(cpu, rows) if r[1] > 0] or cpu))
            summary.setdefault(label, {})[variant] = cpu_ms
            rec.record(f"kinema-{name}-{variant}", label, sec, iterations=round(newton), measurement=m,
                       notes={"contacts": contacts, "newton": f"{newton:.1f}", "ccd_share": f"{ccd:.2f}",
                              "solve_share": f"{solve:.2f}", "analyses_per_iteration": f"{analyses:.2f}",
                              "vertices": len(scene.x),
                              "cpu_ms": f"{cpu_ms:.1f}"})
            print(f"{label:14s} {variant:20s} {sec * 1e3:8.1f} ms/step (cpu {cpu_ms:6.1f} ms)  contacts {contacts:5d}  "
                  f"newton {newton:5.1f}  ccd {ccd:.0%}  solve {solve:.0%}  analyses/iteration {analyses:.2f}  "
                  f"(other load {m.other_load:.2f})", flush=True)
    if len(variants) > 1:
        print("summary (CPU ms per step with contact, by linear-solver variant): " + "; ".join(
            f"{label}: " + ", ".join(f"{v} {ms:.1f}" for v, ms in row.items()) for label, row in summary.items()))


def kernel_case(scene, dt, warm_steps):
    for _ in range(warm_steps):
        scene.step(dt)
    x0 = scene.x.copy()
    scene.step(dt)
    x1 = scene.x.copy()
    scene.set_state({**scene.state(), "x": x0})
    return x0, x1


def cpu_seconds(fn, calls=20, repeats=5):
    """Least CPU time (all threads of the process) per call over `repeats` batches of `calls`:
    on a machine shared with other jobs it moves much less than wall time."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        for _ in range(calls):
            fn()
        best = min(best, (time.process_time() - t) / calls)
    return best


def kernels_side_by_side(rec, quick):
    import ipctk

    ipctk.set_num_threads(1)  # both sides single-threaded

    cases = [("pile 4 cubes n=3", lambda: pile(4, 3), 40), ("cloth 16x16 on sphere", lambda: cloth(16), 10)]
    if quick:
        cases = [("pile 4 cubes n=2", lambda: pile(4, 2), 40), ("cloth 12x12 on sphere", lambda: cloth(12), 10)]
    for label, make, warm in cases:
        scene, dt = make()
        x0, x1 = kernel_case(scene, dt, warm)
        dhat = scene.config.dhat
        # Planes are not part of an ipctk mesh: compare on the mesh pairs only (the pile's
        # ground contacts are vertex-plane, so the pile's mesh pairs are cube-cube).
        mesh = ipctk.CollisionMesh(np.asfortranarray(x0), np.asfortranarray(scene.edges.astype(np.int32)),
                                   np.asfortranarray(scene.faces.astype(np.int32)))
        B = ipctk.BarrierPotential(dhat, 1.0)

        def ipc_build():
            c = ipctk.NormalCollisions()
            c.build(mesh, np.asfortranarray(x0), dhat)
            return c

        c = ipc_build()
        ipc_count = len(c)
        ours = scene._core.constraint_count(x0)

        # Check kinema's gradient before timing it.
        rng = np.random.default_rng(0)
        u = rng.normal(size=x0.shape) * (scene.mass > 0)[:, None]
        u /= np.linalg.norm(u)
        eps = 1e-7
        fd = (scene.barrier_energy(x0 + eps * u) - scene.barrier_energy(x0 - eps * u)) / (2 * eps)
        g = scene.barrier_gradient(x0)
        assert abs(fd - np.sum(g * u)) <= 1e-4 * np.abs(g).sum() + 1e-30, (fd, np.sum(g * u))
        size = f"{label}, {len(x0)} vertices, {len(scene.faces)} faces"

        def ipc_distance():
            return ipc_build().compute_minimum_distance(mesh, np.asfortranarray(x0))

        timings = {
            "distance": (lambda: scene._core.constraint_count(x0), ipc_distance),
            "barrier": (lambda: scene.barrier_energy(x0), lambda: B(ipc_build(), mesh, np.asfortranarray(x0))),
            "gradient": (lambda: scene.barrier_gradient(x0),
                         lambda: B.gradient(ipc_build(), mesh, np.asfortranarray(x0))),
            "hessian": (lambda: scene.barrier_hessian(x0, project=True),
                        lambda: B.hessian(ipc_build(), mesh, np.asfortranarray(x0),
                                          project_hessian_to_psd=ipctk.PSDProjectionMethod.CLAMP)),
        }
        for kernel, (ours_fn, theirs_fn) in timings.items():
            mo = harness.measure(ours_fn, min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
            mt = harness.measure(theirs_fn, min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
            co, ct = cpu_seconds(ours_fn), cpu_seconds(theirs_fn)
            rec.record(f"kinema-{kernel}", size, mo.seconds, measurement=mo, notes={"pairs": ours, "cpu_ms": f"{co * 1e3:.3f}"})
            rec.record(f"ipctk-{kernel}", size, mt.seconds, measurement=mt, notes={"pairs": ipc_count, "cpu_ms": f"{ct * 1e3:.3f}"})
            print(f"{size}: {kernel:8s} kinema {mo.seconds * 1e3:8.3f} ms ({ours} pairs)  "
                  f"ipctk {mt.seconds * 1e3:8.3f} ms ({ipc_count} collisions)  ratio {mt.seconds / mo.seconds:5.2f}x  "
                  f"| cpu kinema {co * 1e3:.3f} ms ipctk {ct * 1e3:.3f} ms ratio {ct / co:5.2f}x")

        dx = x1 - x0
        far = x0 + 3 * dx  # a longer move, so the step is clamped
        t_ours = scene.max_safe_step(far - x0, x=x0)
        t_tight = ipctk.compute_collision_free_stepsize(mesh, np.asfortranarray(x0), np.asfortranarray(far))
        t_add = ipctk.compute_collision_free_stepsize(mesh, np.asfortranarray(x0), np.asfortranarray(far),
                                                      narrow_phase_ccd=ipctk.AdditiveCCD())
        for t in (t_ours, t_tight, t_add):
            y = x0 + t * (far - x0)
            assert not scene.intersections(x=y) and scene.min_distance(x=y) > 0
        mo = harness.measure(lambda: scene.max_safe_step(far - x0, x=x0), min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
        mt = harness.measure(lambda: ipctk.compute_collision_free_stepsize(mesh, np.asfortranarray(x0),
                                                                           np.asfortranarray(far)),
                             min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
        ma = harness.measure(lambda: ipctk.compute_collision_free_stepsize(
            mesh, np.asfortranarray(x0), np.asfortranarray(far), narrow_phase_ccd=ipctk.AdditiveCCD()),
            min_of=3, warmup=True, quiet_timeout=2, max_tries=4)
        co = cpu_seconds(lambda: scene.max_safe_step(far - x0, x=x0))
        ct = cpu_seconds(lambda: ipctk.compute_collision_free_stepsize(mesh, np.asfortranarray(x0), np.asfortranarray(far)))
        ca = cpu_seconds(lambda: ipctk.compute_collision_free_stepsize(
            mesh, np.asfortranarray(x0), np.asfortranarray(far), narrow_phase_ccd=ipctk.AdditiveCCD()))
        rec.record("kinema-ccd", size, mo.seconds, measurement=mo, notes={"step": f"{t_ours:.4f}", "cpu_ms": f"{co * 1e3:.3f}"})
        rec.record("ipctk-ccd-tight-inclusion", size, mt.seconds, measurement=mt,
                   notes={"step": f"{t_tight:.4f}", "cpu_ms": f"{ct * 1e3:.3f}"})
        rec.record("ipctk-ccd-additive", size, ma.seconds, measurement=ma, notes={"step": f"{t_add:.4f}", "cpu_ms": f"{ca * 1e3:.3f}"})
        print(f"{size}: ccd      kinema {mo.seconds * 1e3:8.3f} ms (t={t_ours:.4f})  ipctk tight-inclusion "
              f"{mt.seconds * 1e3:8.3f} ms (t={t_tight:.4f})  ipctk additive {ma.seconds * 1e3:8.3f} ms (t={t_add:.4f})  "
              f"| cpu kinema {co * 1e3:.3f} ms, ipctk {ct * 1e3:.3f} / {ca * 1e3:.3f} ms")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                        help="linear-solver variants of the per-step sweep")
    parser.add_argument("--no-kernels", action="store_true", help="skip the kernels beside ipctk")
    parser.add_argument("--out", type=Path, default=Path("bench/out"))
    args = parser.parse_args(argv)
    km.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    args.out.mkdir(parents=True, exist_ok=True)
    rec = harness.Recorder(args.out / "contact.csv", benchmark="contact")
    print(f"commit {harness.git_commit()}  threads 1")
    solver_sweep(rec, args.quick, args.variants)
    if not args.no_kernels:
        kernels_side_by_side(rec, args.quick)


if __name__ == "__main__":
    main()
