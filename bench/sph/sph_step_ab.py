"""Before/after comparison of km.sph time steps between two installed builds of kinema, on the
3D dam break of sph_bench.py (148,176 particles, DFSPH dt 1.07e-3 at tol 1e-3, WCSPH at its
acoustic CFL step). Each (build, method, threads) run is a fresh process, and the builds are
alternated round by round, so that a shared machine's load falls on both alike.

    python bench/sph/sph_step_ab.py BEFORE_PYTHON AFTER_PYTHON [--rounds 3] [--steps 10] [--tol 1e-3]

e.g. ``python bench/sph/sph_step_ab.py build/venv-before/bin/python .venv/bin/python`` (a build is
named by its Python interpreter; a wrapper script that sets PYTHONPATH names a copied install). A run starts
as sph_bench.py's does (advance to START, one untimed step at the timed dt), times `steps`
steps and reports CPU and wall milliseconds per step, the other processes' load during the
timed window (harness.other_load, in cores), and for DFSPH the iterations per step and the
mean density error, which must agree between the builds (the comparison is of equal work).
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


def stat(st, name):
    """A field of a step's stats: a StepStats object, or the dict older builds returned."""
    return st[name] if isinstance(st, dict) else getattr(st, name)


def worker(method: str, steps: int, tol: float = 1e-3) -> None:
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(HERE.parent / "common"))  # harness.py
    import harness
    import sph_bench as sb

    fluid, s = sb.kinema_fluid(150_000, method, tol)  # tol and divergence_tol (DFSPH)
    dt = sb.started_dt(fluid, method, s)
    fluid.step(dt)
    its, errors = [], []
    before = harness.sample_cpu()
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(steps):
        st = fluid.step(dt)
        its.append(stat(st, "iterations") + stat(st, "divergence_iterations"))
        errors.append(stat(st, "density_error"))
    cpu = (time.process_time() - cpu) / steps * 1e3
    wall = (time.perf_counter() - wall) / steps * 1e3
    load = harness.other_load(before, harness.sample_cpu())
    print(json.dumps(dict(cpu_ms=cpu, wall_ms=wall, other_load=load, iterations=sum(its) / steps,
                          density_error=sum(errors) / steps, dt=dt)))


def run(python: str, method: str, threads: int, steps: int, tol: float) -> dict:
    env = {"OMP_NUM_THREADS": str(threads), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([python, __file__, "--worker", method, "--steps", str(steps), "--tol", str(tol)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", nargs="?")
    ap.add_argument("after", nargs="?")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--methods", default="dfsph,wcsph")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--tol", type=float, default=1e-3, help="DFSPH tol and divergence_tol")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.steps, args.tol)
        return
    builds = {"before": args.before, "after": args.after}
    results = {}
    for r in range(args.rounds):
        for method in args.methods.split(","):
            for threads in map(int, args.threads.split(",")):
                for name, python in builds.items():
                    res = run(python, method, threads, args.steps, args.tol)
                    results.setdefault((method, threads, name), []).append(res)
                    print(f"round {r} {method} {threads} thread(s) {name}: {res['cpu_ms']:.1f} CPU ms / "
                          f"{res['wall_ms']:.1f} ms per step, other_load {res['other_load']:.2f}, "
                          f"{res['iterations']:.2f} iterations, density error {res['density_error']:.3e}",
                          flush=True)
    print("\n| method | threads | before CPU / wall ms | after CPU / wall ms | speed-up (CPU, wall) | other_load |")
    print("| --- | --- | --- | --- | --- | --- |")
    for method in args.methods.split(","):
        for threads in map(int, args.threads.split(",")):
            med = {n: {k: statistics.median(x[k] for x in results[(method, threads, n)])
                       for k in ("cpu_ms", "wall_ms")} for n in builds}
            loads = [x["other_load"] for n in builds for x in results[(method, threads, n)]]
            b, a = med["before"], med["after"]
            print(f"| {method} | {threads} | {b['cpu_ms']:.1f} / {b['wall_ms']:.1f} | {a['cpu_ms']:.1f} / "
                  f"{a['wall_ms']:.1f} | {b['cpu_ms'] / a['cpu_ms']:.2f}x, {b['wall_ms'] / a['wall_ms']:.2f}x | "
                  f"{min(loads):.2f}-{max(loads):.2f} |")


if __name__ == "__main__":
    main()
