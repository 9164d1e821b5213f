"""A/B of the 3D FMM between two installed builds of kinema: one-thread CPU seconds per call,
the two interpreters alternated round by round so that both see the same machine load.

    python bench/fmm/fmm3d_ab.py A_PYTHON B_PYTHON [--n 200000] [--eps 1e-6] [--rounds 5]

Cases: laplace (km.fmm.laplace3d, phi and gradient, the targets being the sources; with
phi's relative error at 300 sampled sources), plane (the same on points of the plane z = 0,
not a Plummer sphere; --cases plane,laplace), plummer
(the near kernel of km.nbody: softening 0.01, leaves >= 20 softenings, phi and gradient) and
gaussian (km.vortex.VortexParticles3D's kernel: core 0.01, leaves >= 6 cores, 3 components,
phi, gradient and Hessian; at n / 4 points), on a Plummer sphere. Prints per case the best
(minimum) CPU seconds of each build over the rounds, their spread and B/A, the other
processes' load (cores) during each child (bench/common/harness.py), and a one-line summary.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))
import harness  # noqa: E402

CHILD = r"""
import json, sys, time
import numpy as np
import kinema as km
km.set_num_threads(1)
case, n, eps, reps = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
x, _, _ = km.nbody.plummer(n, seed=3)
q = np.random.default_rng(4).uniform(0.5, 1.5, n)
if case == "plane":  # the points on z = 0 (a flat set: the tree's root shift)
    x = np.c_[np.random.default_rng(6).random((n, 2)), np.zeros(n)]
if case in ("laplace", "plane"):
    call = lambda: km.fmm.laplace3d(x, q, eps=eps, gradient=True)
elif case == "plummer":
    call = lambda: km.fmm._eval3d(x, q, None, eps=eps, derivatives=1, kernel="plummer",
                                  length=0.01, min_width=0.2)
else:
    q3 = np.random.default_rng(5).uniform(-1, 1, (n, 3))
    call = lambda: km.fmm._eval3d(x, q3, None, eps=eps, derivatives=2, kernel="gaussian",
                                  length=0.01, min_width=0.06)
call()
best = float("inf")
for _ in range(reps):
    t = time.process_time()
    call()
    best = min(best, time.process_time() - t)
err = None
if case in ("laplace", "plane"):  # phi's relative 2-norm error at 300 sampled sources
    sub = np.random.default_rng(7).choice(n, 300, replace=False)
    ref = km.fmm.direct3d(x, q, x[sub])
    err = float(np.linalg.norm(call()[0][sub] - ref) / np.linalg.norm(ref))
print(json.dumps({"cpu": best, "err": err}))
"""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--n", type=int, default=200_000)
    ap.add_argument("--eps", type=float, default=1e-6)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--cases", default="laplace,plummer,gaussian")
    args = ap.parse_args()
    env_note = "OMP 1 thread"
    summary = []
    for case in args.cases.split(","):
        n = args.n // 4 if case == "gaussian" else args.n
        times = {"A": [], "B": []}
        errs = {}
        loads = []
        for r in range(args.rounds):
            for name in (("A", "B") if r % 2 == 0 else ("B", "A")):
                py = args.a if name == "A" else args.b
                before = harness.sample_cpu()
                res = subprocess.run([py, "-c", CHILD, case, str(n), str(args.eps), str(args.reps)],
                                     capture_output=True, text=True, check=True,
                                     env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
                loads.append(harness.other_load(before, harness.sample_cpu()))
                out = json.loads(res.stdout.strip().splitlines()[-1])
                times[name].append(out["cpu"])
                errs[name] = out.get("err")
        a, b = min(times["A"]), min(times["B"])
        err = (f"  error A {errs['A']:.2e} B {errs['B']:.2e}" if errs.get("A") is not None
               and errs.get("B") is not None else "")
        print(f"{case:8s} n={n:7d} eps={args.eps:g}  A {a:.3f} s (max {max(times['A']):.3f})  "
              f"B {b:.3f} s (max {max(times['B']):.3f})  B/A {b / a:.3f}{err}  "
              f"other load {min(loads):.2f}-{max(loads):.2f} cores  ({env_note})")
        summary.append(f"{case} B/A {b / a:.3f}")
    print("summary: " + ", ".join(summary))


if __name__ == "__main__":
    main()
