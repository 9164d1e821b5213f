"""A/B of the explicit steps' stability checks: time per single-step call of two builds, run in
alternating rounds on one thread (the machine is shared: the figure is process CPU time per
step, best of 5 blocks, with the other processes' load recorded).

Cases: km.massspring's damped 128 x 128 cloth, symplectic (structural springs only, 32,512,
and all of cloth()'s 97,026), km.fem's symplectic step on box meshes of 384 and 24,576
tetrahedra, km.mpm's mpm88 and mpm128 scenes (those of mpm/mpm_bench.py). Usage:

    .venv/bin/python bench/explicit_limits_ab.py --builds /path/to/main/.venv/bin/python .venv/bin/python

The first build is the reference; the summary gives each case's time per step in each build
and the ratio reference / build (above 1: the build is faster).
"""
import argparse
import json
import subprocess
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent


def worker():
    import numpy as np

    import kinema as km

    sys.path.insert(0, str(HERE / "common"))
    sys.path.insert(0, str(HERE / "mpm"))
    import harness
    from mpm_bench import kinema_scene

    km.set_num_threads(1)
    # Taichi's mpm128 step (1e-4 s) is at CFL 1.04 for kinema's estimate: its warning, formatted
    # each step in both builds, is not printed.
    warnings.simplefilter("ignore", RuntimeWarning)
    out = {}

    def timed(name, step, per_block):
        for _ in range(max(3, per_block // 4)):  # warm-up
            step()

        def block():
            c0 = time.process_time()
            for _ in range(per_block):
                step()
            return (time.process_time() - c0) / per_block

        m = harness.measure(block, min_of=5, figure=lambda value, wall: value, quiet_timeout=2.0)
        out[name] = {"cpu": m.seconds, "other_load": m.other_load, "disturbed": m.disturbed}

    x, springs, kinds = km.massspring.cloth(128, 128, 1.0, return_kinds=True)
    for label, keep in (("cloth128 structural", kinds == 0), ("cloth128 all springs", kinds >= 0)):
        s = km.massspring.System(x, springs[keep], stiffness=1e3, mass=1e-3, damping=0.01, fixed=[0, 127],
                                 gravity=(0, -9.81, 0))
        dt = 0.5 * s.explicit_dt_limit
        timed(f"massspring {label} ({int(keep.sum())} springs)", lambda: s.step(dt, "symplectic"), 40)
    for n in (4, 16):
        v, t = km.fem.box_mesh((0, 0, 0), (1, 1, 1), n)
        body = km.fem.Body(v, t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0, damping=0.5,
                           fixed=np.flatnonzero(v[:, 1] == 0), gravity=(0, -9.81, 0))
        dt = 0.5 * body.explicit_dt_limit
        timed(f"fem box {len(t)} tets", lambda: body.step(dt, "symplectic"), 400 if n == 4 else 20)
    rng = np.random.default_rng(1)
    for kind in ("mpm88", "mpm128"):
        if kind == "mpm88":
            start = dict(x=rng.random((8192, 2)) * 0.4 + 0.2, v=np.zeros((8192, 2)), n_grid=128)
            dt = 2e-4
        else:
            g = 3000
            xs = np.concatenate([rng.random((g, 2)) * 0.2 + [0.3 + 0.1 * i, 0.05 + 0.32 * i] for i in range(3)])
            start = dict(x=xs, v=np.zeros((3 * g, 2)), n_grid=128, gravity=[0, -50.0], material=np.repeat([0, 1, 2], g))
            dt = 1e-4
        sim = kinema_scene(kind, start, adapt_threads=False)
        timed(f"mpm {kind}", lambda: sim.step(dt), 100)
    print(json.dumps(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--builds", nargs=2, metavar="PYTHON", help="reference and new interpreters")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    opts = ap.parse_args()
    if opts.worker:
        return worker()
    best = [dict(), dict()]
    for r in range(opts.rounds):
        for b, python in enumerate(opts.builds):
            env = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
            import os
            res = subprocess.run([python, str(Path(__file__).resolve()), "--worker"], capture_output=True, text=True,
                                 env=os.environ | env, check=True)
            for case, m in json.loads(res.stdout.strip().splitlines()[-1]).items():
                if case not in best[b] or m["cpu"] < best[b][case]["cpu"]:
                    best[b][case] = m
            print(f"round {r + 1} build {b + 1} done", flush=True)
    print(f"{'case':45s} {'reference ms':>12s} {'build ms':>10s} {'ratio':>7s}  other load (ref, build)")
    summary = []
    for case, ref in best[0].items():
        new = best[1][case]
        ratio = ref["cpu"] / new["cpu"]
        flag = " (disturbed)" if ref["disturbed"] or new["disturbed"] else ""
        print(f"{case:45s} {ref['cpu'] * 1e3:12.4f} {new['cpu'] * 1e3:10.4f} {ratio:7.3f}  "
              f"{ref['other_load']:.2f}, {new['other_load']:.2f}{flag}")
        summary.append(f"{case} {ratio:.2f}x")
    print("summary, reference / build CPU time per single-step call, 1 thread: " + "; ".join(summary))


if __name__ == "__main__":
    main()
