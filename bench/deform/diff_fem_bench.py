"""Gradients through the neo-Hookean cube: backward time against forward time, stored and
checkpointed, with peak memory (km.diff over km.fem.Body).

The cube of bench/deform/deform_bench.py: 20^3 vertices, 19^3 cells x 5 = 34,295 tetrahedra, E = 5e4,
nu = 0, rho = 1000, gravity -9.8 y, an initial velocity with a shear; T implicit steps of
h = 0.01, Newton to a relative gradient norm of 1e-6 with the default linear solver (PCG with
the lagged CHOLMOD factor). Gradient of L = w . x_T with respect to x_0, v_0 and the per-element
Young's modulus.

- forward: T plain steps (after one untimed step that pays the CHOLMOD analysis);
- stored: km.diff.rollout (every state kept) and its backward pass;
- checkpointed: checkpoints = K = ceil(2 sqrt(T)) (binomial schedule), rollout and backward
  (the backward recomputes forward steps);
- peak memory: the peak of Python-side allocations (tracemalloc: the states km.diff holds) during
  rollout + backward, in units of one state (x, v and the factor record: 3 n d floats).
Before timing, the benchmark checks its gradient: the directional derivative along a random
direction of v_0 against a central difference of two forward runs, and the checkpointed
gradients against the stored ones (bitwise).

    .venv/bin/python bench/deform/diff_fem_bench.py [--steps 16] [--quick]
    .venv/bin/python bench/deform/diff_fem_bench.py --baseline DIR   (forward step against the kinema
        package in DIR, e.g. an older build, alternated in one run)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"
DT = 0.01


def cube_body(n, per_element=True):
    V, T = km.fem.box_mesh([0, 1, 0], [1, 2, 1], n - 1, tets_per_cell=5)
    E = np.full(len(T), 5e4) if per_element else 5e4
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=E,
                       poisson_ratio=0.0, density=1000.0, gravity=(0, -9.8, 0))
    body.v[:, 0] = 1.0
    body.v[V[:, 1] > 1.5, 2] = 0.5  # a shear so that Newton has work beyond free fall
    return body


def warm(n, per_element=True):
    """A body after one untimed step (CHOLMOD's analysis and first factorisation)."""
    body = cube_body(n, per_element)
    body.step(DT)
    return body


def state_bytes(body):
    return sum(np.asarray(v).nbytes for v in body.state().values())


def check_gradient(n, steps, w):
    """Directional derivative along a random direction of v_0 against central differences."""
    body = warm(n)
    start = body.state()
    run = km.diff.rollout(body, steps, DT, wrt=("v",))
    g = run.backward({"x": w})["v"]
    e = np.random.default_rng(1).standard_normal(g.shape)
    h = 1e-3  # [m/s]: truncation ~ h^2 |L'''| ~ 1e-6 relative, Newton's tol 1e-6 / h far below

    def loss(t):
        b = warm(n)
        s = dict(start)
        s["v"] = start["v"] + t * e
        b.set_state(s)
        for _ in range(steps):
            b.step(DT)
        return float((w * b.x).sum())

    fd = (loss(h) - loss(-h)) / (2 * h)
    ad = float((g * e).sum())
    rel = abs(ad - fd) / abs(fd)
    print(f"check: adjoint {ad:.8e}, central difference {fd:.8e}, relative difference {rel:.1e}")
    assert rel < 1e-3, f"gradient check failed: relative difference {rel:.2e}"
    return rel


def forward_seconds(n, steps, per_element=True):
    body = warm(n, per_element)
    start = time.perf_counter()
    for _ in range(steps):
        assert body.step(DT).converged
    return (time.perf_counter() - start) / steps


def gradient_run(n, steps, checkpoints, w, wrt):
    """(rollout seconds, backward seconds, peak memory in states, gradients, states held).
    tracemalloc sees Python's allocations only: a run stored whole keeps its states in C++
    (km.fem's _diff_record), so the stored figure is km.diff's count of states held."""
    body = warm(n)
    unit = state_bytes(body)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    run = km.diff.rollout(body, steps, DT, wrt=wrt, checkpoints=checkpoints)
    t1 = time.perf_counter()
    grads = run.backward({"x": w})
    t2 = time.perf_counter()
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return t1 - t0, t2 - t1, peak / unit, grads, run.peak_states


def child(n, steps):
    print(json.dumps({"forward": forward_seconds(n, steps, per_element=False), "kinema": km.__file__}))


def baseline(args):
    """Forward step time of this kinema against the one in args.baseline, alternated."""
    script = Path(__file__).resolve()
    times = {"current": [], "baseline": []}
    for _ in range(args.rounds):
        for which, path in (("current", None), ("baseline", args.baseline)):
            env = dict(os.environ)
            if path:  # PYTHONPATH comes before site-packages: that folder's kinema is imported
                env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(path), env.get("PYTHONPATH")]))
            before = harness.sample_cpu()
            out = subprocess.run([sys.executable, str(script), "--child", "--n", str(args.n), "--steps",
                                  str(args.steps)], capture_output=True, text=True, check=True, env=env)
            load = harness.other_load(before, harness.sample_cpu())
            value = json.loads(out.stdout.strip().splitlines()[-1])
            times[which].append((value["forward"], load))
            print(f"{which:8s} {value['kinema']}: {value['forward']:.3f} s/step (other load {load:.2f})")
    best = {k: min(t for t, _ in v) for k, v in times.items()}
    print(f"forward step, best of {args.rounds}: current {best['current']:.3f} s, baseline "
          f"{best['baseline']:.3f} s, ratio current/baseline {best['current'] / best['baseline']:.3f}")
    return best


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=20, help="vertices per cube edge")
    parser.add_argument("--steps", type=int, default=16)
    parser.add_argument("--quick", action="store_true", help="small cube, few steps (smoke run)")
    parser.add_argument("--baseline", type=Path, help="folder holding another kinema package")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.quick:
        args.n, args.steps = 6, 4
    if args.child:
        return child(args.n, args.steps)
    if args.baseline:
        return baseline(args)
    n, steps = args.n, args.steps
    K = math.ceil(2 * math.sqrt(steps))
    w = np.random.default_rng(0).standard_normal(cube_body(n).x.shape)
    tets = len(cube_body(n).elements)
    rel = check_gradient(n, steps, w)
    wrt = ("x", "v", "youngs_modulus")
    rec = harness.Recorder(OUT / "diff_fem.csv", "diff_fem")
    size = f"{n}^3 verts, {tets} tets, T={steps}"

    fwd = harness.measure(lambda: forward_seconds(n, steps), figure=lambda v, wall: v)
    F = fwd.seconds
    rec.record("forward_step", size, F, measurement=fwd)
    results = {}
    for label, k in (("stored", None), ("checkpointed", K)):
        m = harness.measure(lambda k=k: gradient_run(n, steps, k, w, wrt),
                            figure=lambda v, wall: v[1])
        roll, back, peak, grads, held = m.value
        results[label] = grads
        rec.record(f"backward_{label}", size, back / steps, error=rel, measurement=m,
                   notes={"checkpoints": k or steps + 1, "rollout_per_step": f"{roll / steps:.4f}",
                          "backward_over_forward": f"{back / steps / F:.3f}",
                          "peak_states": f"{peak:.1f}", "states_held": held})
        print(f"{label:12s} (K = {k or 'all'}): rollout {roll / steps:.3f} s/step, backward "
              f"{back / steps:.3f} s/step = {back / steps / F:.2f} x forward ({F:.3f} s/step); "
              f"peak memory {peak:.1f} states in Python, {held} held in all (3 sqrt(T) = "
              f"{3 * math.sqrt(steps):.1f}); "
              f"other load {m.other_load:.2f}, {m.repeats} tries")
    for name in wrt:
        assert np.array_equal(results["stored"][name], results["checkpointed"][name]), name
    print(f"cube {n}^3 ({tets} tets), T = {steps}, K = {K}: checkpointed gradients equal the stored "
          f"ones bitwise; threads {harness.default_threads()}, commit {harness.git_commit()}")


if __name__ == "__main__":
    main()
