"""Before/after comparison of km.grid steps and km.poisson solves between two installed builds
of kinema. Each (build, case) run is a fresh process and the builds alternate round by round,
so that a shared machine's load falls on both alike.

    python bench/grid_ab.py BEFORE_PYTHON AFTER_PYTHON [--rounds 3] [--steps 4]

BEFORE_PYTHON / AFTER_PYTHON: interpreters importing each build (a wrapper script that sets
PYTHONPATH to a build's site directory will do). Cases: the smoke step of grid_bench.py
(2D 512^2 and 3D 64^3: MacCormack, buoyancy, vorticity confinement, an obstacle, MGPCG to
1e-6) and MGPCG Poisson solves (2D 1024^2 and 3D 128^3 Dirichlet, tol 1e-8). A run times
`steps` repetitions after one untimed one and reports CPU and wall milliseconds each, the
other processes' load (harness.other_load, in cores) and a fingerprint of the result (the
pressure iterations and the final field's sum), which must agree between the builds: the
comparison is of equal work, and a refactoring that keeps the results bitwise keeps it exactly.
The table gives each build's median over the rounds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
CASES = ("smoke2d", "smoke3d", "poisson2d", "poisson3d")


def worker(case: str, steps: int) -> None:
    sys.path.insert(0, str(HERE))
    import numpy as np

    import grid_bench as gb
    import harness
    import kinema as km

    if case.startswith("smoke"):
        shape = (512, 512) if case == "smoke2d" else (64, 64, 64)
        f, src = gb.smoke(shape)
        dt = 0.5 / shape[0]

        def once():
            f.density[src] = 1.0
            f.temperature[src] = 1.0
            return f.step(dt).pressure.iterations

        fingerprint = lambda: float(f.density.sum() + f.pressure.sum())  # noqa: E731
    else:
        shape = (1024, 1024) if case == "poisson2d" else (128, 128, 128)
        s = km.poisson.Solver(shape, 1 / shape[0], "dirichlet")
        b = np.random.default_rng(0).normal(size=shape)
        result = {}

        def once():
            u, info = s.solve(b, tol=1e-8)
            result["u"] = u
            return info.iterations

        fingerprint = lambda: float(result["u"].sum())  # noqa: E731
    once()
    its = []
    before = harness.sample_cpu()
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(steps):
        its.append(once())
    cpu = (time.process_time() - cpu) / steps * 1e3
    wall = (time.perf_counter() - wall) / steps * 1e3
    load = harness.other_load(before, harness.sample_cpu())
    print(json.dumps(dict(cpu_ms=cpu, wall_ms=wall, other_load=load, iterations=sum(its) / steps,
                          fingerprint=fingerprint())))


def run(python: str, case: str, threads: int, steps: int) -> dict:
    env = {"OMP_NUM_THREADS": str(threads), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([python, __file__, "--worker", case, "--steps", str(steps)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", nargs="?")
    ap.add_argument("after", nargs="?")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--threads", default="2")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.steps)
        return
    builds = {"before": args.before, "after": args.after}
    cases = args.cases.split(",")
    threads_list = list(map(int, args.threads.split(",")))
    results = {}
    for r in range(args.rounds):
        for case in cases:
            for threads in threads_list:
                for name, python in builds.items():
                    res = run(python, case, threads, args.steps)
                    results.setdefault((case, threads, name), []).append(res)
                    print(f"round {r} {case} {threads} thread(s) {name}: {res['cpu_ms']:.1f} CPU ms / "
                          f"{res['wall_ms']:.1f} ms, other_load {res['other_load']:.2f}, "
                          f"{res['iterations']:.1f} iterations, fingerprint {res['fingerprint']!r}", flush=True)
    print("\n| case | threads | before CPU / wall ms | after CPU / wall ms | speed-up (CPU, wall) | other_load | same result |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for case in cases:
        for threads in threads_list:
            runs = {n: results[(case, threads, n)] for n in builds}
            med = {n: {k: statistics.median(x[k] for x in runs[n]) for k in ("cpu_ms", "wall_ms")} for n in builds}
            loads = [x["other_load"] for n in builds for x in runs[n]]
            same = len({(x["iterations"], x["fingerprint"]) for n in builds for x in runs[n]}) == 1
            b, a = med["before"], med["after"]
            print(f"| {case} | {threads} | {b['cpu_ms']:.1f} / {b['wall_ms']:.1f} | {a['cpu_ms']:.1f} / "
                  f"{a['wall_ms']:.1f} | {b['cpu_ms'] / a['cpu_ms']:.2f}x, {b['wall_ms'] / a['wall_ms']:.2f}x | "
                  f"{min(loads):.2f}-{max(loads):.2f} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
