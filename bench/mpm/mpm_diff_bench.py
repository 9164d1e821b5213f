"""Gradient cost of km.mpm through km.diff on a 2D diffmpm-size task (Hu et al. 2020: an elastic
body of ~3,300 particles on a 128^2 grid, dt = 1e-3), against DiffTaichi's diffmpm gradient on
Taichi's CPU backend (bench/mpm/mpm_diff_taichi_peer.py, run in its own process) in one run.

    .venv/bin/python bench/mpm/mpm_diff_bench.py [--steps 256] [--threads 2] [--csv bench/out/mpm_diff.csv]

Same task on both sides: a fixed-corotated block (E = 4 kPa, nu = 0.2, rho = 1000) with
gravity, sticky walls, random initial velocities and per-step particle forces; the loss is the
mean x of the particles after the run; the gradient is taken with respect to the initial
velocities and the forces. Reported per side: forward seconds, seconds per gradient (forward +
backward), and the agreement of the directional derivative along a random direction of the
initial velocities with its own central difference (|adjoint - FD| / |FD|). kinema also reports
backward / forward with every state stored and with 2 sqrt(T) checkpoints.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

CSV = Path(__file__).resolve().parents[1] / "out" / "mpm_diff.csv"


def task(steps, grid):
    h = 1.0 / grid
    x0 = km.mpm.block([0.1, 0.03], [0.4, 0.2], h / 2)
    sim = km.mpm.Simulation((grid, grid), h, gravity=(0.0, -9.81), boundary="sticky")
    sim.add_particles(x0, "elastic", density=1000.0, youngs_modulus=4e3, poisson_ratio=0.2)
    rng = np.random.default_rng(0)  # the peer draws v0, the forces and the direction in this order
    sim.v[...] = rng.normal(0, 0.1, (sim.count, 2))
    forces = rng.normal(0, 1e-4, (steps, sim.count, 2))
    direction = rng.normal(size=(sim.count, 2))
    return sim, x0, forces, direction


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=256)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--dt", type=float, default=1e-3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--csv", type=Path, default=CSV)
    ap.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD)
    ap.add_argument("--no-taichi", action="store_true")
    opts = ap.parse_args()
    km.set_num_threads(opts.threads)
    steps, dt = opts.steps, opts.dt
    sim, x0, forces, direction = task(steps, opts.grid)
    n = sim.count
    s0 = sim.state()
    grads_in = {"x": np.column_stack([np.full(n, 1.0 / n), np.zeros(n)])}
    rec = harness.Recorder(opts.csv, "mpm_diff_2d", threads=opts.threads)

    def plain():
        sim.set_state(s0)
        for k in range(steps):
            sim._sim.step(dt, forces[k])
        return float(sim.x[:, 0].mean())

    def gradient(checkpoints):
        def run():
            sim.set_state(s0)
            t0 = time.perf_counter()
            r = km.diff.rollout(sim, steps, dt, wrt=("v", "controls"), controls=forces, checkpoints=checkpoints)
            t1 = time.perf_counter()
            g = r.backward(grads_in)
            t2 = time.perf_counter()
            return {"forward": t1 - t0, "backward": t2 - t1, "g": g, "peak": r.peak_states}
        return run

    # One step and its adjoint alone (C++, best of 30): the solver's own backward/forward,
    # without km.diff's bookkeeping.
    sim.set_state(s0)
    sim._sim.step(dt, forces[0])
    s1 = sim.state()
    g1 = {k: np.ones_like(s1[k]) for k in ("x", "v", "F", "C")}

    def best_of(fn, reps=30):
        return harness.best_of(fn, reps)

    sim.set_state(s0)
    t_step = best_of(lambda: sim._sim.step(dt, forces[0]))
    t_adj = best_of(lambda: sim._sim.step_adjoint(dt, s0, s1, forces[0], g1))
    rec.record("kinema-one-step-adjoint", n, t_adj, notes={"step_s": f"{t_step:.4g}", "ratio": f"{t_adj / t_step:.3g}"})
    print(f"kinema one step {t_step * 1e3:.3f} ms, its adjoint {t_adj * 1e3:.3f} ms (ratio {t_adj / t_step:.2f}; "
          f"best of 30)", flush=True)
    fwd = harness.measure(plain, min_of=3, max_load=opts.max_load)
    loss0 = fwd.value
    e = 1e-5
    sim.set_state(s0)
    sim.v[...] += e * direction
    s_plus = sim.state()
    sim.set_state(s0)
    sim.v[...] -= e * direction
    s_minus = sim.state()

    def loss_from(state):
        sim.set_state(state)
        for k in range(steps):
            sim._sim.step(dt, forces[k])
        return float(sim.x[:, 0].mean())

    fd = (loss_from(s_plus) - loss_from(s_minus)) / (2 * e)
    rows = {}
    for label, ck in (("stored", None), ("checkpointed", int(2 * np.sqrt(steps)) + 1)):
        m = harness.measure(gradient(ck), min_of=3, max_load=opts.max_load,
                            figure=lambda v, s: v["forward"] + v["backward"])
        v = m.value
        adj = float((v["g"]["v"] * direction).sum())
        err = abs(adj - fd) / abs(fd)
        ratio = v["backward"] / fwd.seconds
        rows[label] = (m, v, err, ratio)
        rec.record(f"kinema-{label}", n, m.seconds, error=err, measurement=m,
                   notes={"steps": steps, "forward_s": f"{fwd.seconds:.4g}", "backward_s": f"{v['backward']:.4g}",
                          "backward_over_forward": f"{ratio:.3g}", "peak_states": v["peak"]})
        print(f"kinema {label:12s} n={n} steps={steps}: forward {fwd.seconds:.3f} s (plain steps), rollout "
              f"{v['forward']:.3f} s, backward {v['backward']:.3f} s, backward/forward {ratio:.2f}, "
              f"per gradient {m.seconds:.3f} s, peak states {v['peak']}, |adj - FD|/|FD| {err:.2e} "
              f"(load {m.other_load:.2f})", flush=True)
    if opts.no_taichi:
        return
    with tempfile.TemporaryDirectory() as tmp:
        pos = Path(tmp) / "x0.npy"
        np.save(pos, x0)
        peer = Path(__file__).resolve().parent / "mpm_diff_taichi_peer.py"
        for fp in ("f64", "f32"):
            out = subprocess.run([sys.executable, str(peer), str(pos), str(steps), str(dt), str(opts.grid),
                                  "--threads", str(opts.threads), "--fp", fp],
                                 capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            err = abs(res["adjoint"] - res["fd"]) / abs(res["fd"])
            rec.record(f"taichi-diffmpm-{fp}", n, res["gradient_seconds"], error=err,
                       notes={"steps": steps, "forward_s": f"{res['forward_seconds']:.4g}",
                              "loss_gradient_vs_kinema": f"{res['adjoint']:.6g} vs {float((rows['stored'][1]['g']['v'] * direction).sum()):.6g}"})
            print(f"taichi {fp}: forward {res['forward_seconds']:.3f} s, per gradient {res['gradient_seconds']:.3f} s, "
                  f"|adj - FD|/|FD| {err:.2e} (adjoint {res['adjoint']:.8g}, kinema's {float((rows['stored'][1]['g']['v'] * direction).sum()):.8g})",
                  flush=True)
            ratio = res["gradient_seconds"] / rows["stored"][0].seconds
            print(f"  taichi {fp} / kinema stored per gradient: {ratio:.2f}x", flush=True)
    print(f"loss {loss0:.6f}")


if __name__ == "__main__":
    main()
