"""km.contact per step: time per step against contact count (the cube pile and the cloth on a
sphere of examples/contact_scenes.py) with Newton iterations and the CCD's share, by variant of
the Newton system. The kernels beside ipctk are bench/contact/kernel_bench.py; the cloth beside
Newton's VBD, bench/contact/newton_cloth.py.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contact/contact_bench.py [--quick] [--out bench/out]
        [--variants simplicial simplicial-clamp cholmod cholmod-refactorise cholmod-pcg]

Variants: the kept pattern with Eigen's simplicial Cholesky and rank-one barrier Hessians (the
default); the same with each contact's Hessian eigen-clamped instead (the former default); the
kept pattern with CHOLMOD; CHOLMOD re-analysed whenever the contact pattern changes; PCG
preconditioned by a lagged CHOLMOD factor. Every step is checked for penetration (exact minimum
distance > 0, no edge through a triangle). A summary line gives CPU ms per step by variant.
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
    "simplicial-clamp": dict(linear_solver="simplicial", barrier_projection="clamp"),
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


def bench_args(doc, argv, configure=None):
    """The contact benches' command line: --quick, --out and what `configure(parser)` adds;
    one thread for kinema (and OMP_NUM_THREADS=1 for what starts later), --out created."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller cases")
    parser.add_argument("--out", type=Path, default=Path("bench/out"), help="directory of the CSV records")
    if configure is not None:
        configure(parser)
    args = parser.parse_args(argv)
    km.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    args.out.mkdir(parents=True, exist_ok=True)
    return args


def main(argv=None):
    args = bench_args(__doc__, argv, lambda p: p.add_argument(
        "--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
        help="variants of the Newton system in the per-step sweep"))
    rec = harness.Recorder(args.out / "contact.csv", benchmark="contact")
    print(f"commit {harness.git_commit()}  threads 1")
    solver_sweep(rec, args.quick, args.variants)


if __name__ == "__main__":
    main()
