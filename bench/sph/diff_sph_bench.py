"""Gradient cost of km.sph (WCSPH) through km.diff on a flying droplet in 2D and 3D: backward over
forward with every state stored and with K = 2 sqrt(T) checkpoints, peak memory in states, the
C++ step adjoint against one step, and the gradient's agreement with central differences; with
--taichi, the same task's gradient by Taichi's autodiff on its CPU backend
(bench/sph/diff_sph_taichi_peer.py, run in its own process) in the same run.

    .venv/bin/python bench/sph/diff_sph_bench.py [--steps 100] [--threads 2] [--taichi] [--csv bench/out/diff_sph.csv]

Task: a disc (2D, radius 0.25 m) or ball (3D, radius 0.08 m) of water particles at spacing 1 cm
(about 2,000 particles either way), WCSPH with c = 10 m/s, viscosity 1e-4 m^2/s, gravity, random
initial velocities (0.3 m/s) and per-step particle forces, dt = 3e-4 s; loss
L = sum_i w_i . x_i(T) / n with fixed random weights w (internal forces matter: the centre of
mass alone would not see them); the gradient is taken with respect to the initial velocities,
the forces and the viscosity. FD agreement: the directional derivative along a random direction
of the initial velocities against the central difference of the forward as run, for
e = 1e-4, 1e-5, 1e-6 m/s (the best is recorded): large steps move surface particles across
Tait's clamp at rho0, a kink, and small ones meet the noise floor of the forward's
single-precision kernel gradients (tests/test_diff_sph.py); the Taichi peer's adjoint is also
compared with kinema's (the same discrete derivative).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

CSV = Path(__file__).resolve().parents[1] / "out" / "diff_sph.csv"
SPACING = 0.01
FD_STEPS = (1e-4, 1e-5, 1e-6)  # [m/s]


def task(d, steps):
    radius = 0.25 if d == 2 else 0.08
    center = np.full(d, 0.5)
    x = km.sph.block(center - radius, center + radius, SPACING)
    x = x[np.linalg.norm(x - center, axis=1) <= radius]
    rng = np.random.default_rng(d)
    v0 = rng.normal(0, 0.3, x.shape)
    fluid = km.sph.Fluid(x, SPACING, method="wcsph", speed_of_sound=10.0, viscosity=1e-4,
                         gravity=[0.0, -9.81, 0.0][:d], velocity=v0)
    forces = rng.normal(0, 1e-4 * fluid.mass, (steps, fluid.n, d))
    weights = rng.normal(size=x.shape)
    direction = rng.normal(size=x.shape)
    return fluid, x, v0, forces, weights, direction


best_of = harness.best_of


def run_dim(d, opts, rec):
    steps, dt = opts.steps, opts.dt
    fluid, x0, v0, forces, weights, direction = task(d, steps)
    n = fluid.n
    s0 = fluid.state()

    def loss_of_run():
        # sum_i w_i . x_i(T) / n, weights by particle id (rows are reordered during the run)
        x = np.empty_like(fluid.x)
        x[fluid.ids] = fluid.x
        return float((weights * x).sum() / n)

    def plain(state=s0):
        fluid.set_state(state)
        for k in range(steps):
            fluid._core.step(dt, forces[k])
        return loss_of_run()

    # One step and its adjoint alone (C++, best of 20).
    fluid.set_state(s0)
    fluid._core.step(dt, forces[0])
    s1 = fluid.state()
    ones = np.ones((n, d))
    fluid.set_state(s0)
    t_step = best_of(lambda: (fluid.set_state(s0), fluid._core.step(dt, forces[0])), 20)
    t_set = best_of(lambda: fluid.set_state(s0), 20)
    t_adj = best_of(lambda: fluid._core.step_adjoint(dt, s0, s1, ones, ones, True), 20)
    t_step -= t_set
    rec.record(f"kinema-{d}d-one-step-adjoint", n, t_adj,
               notes={"step_s": f"{t_step:.4g}", "ratio": f"{t_adj / t_step:.3g}"})
    print(f"{d}D droplet, {n} particles: one step {t_step * 1e3:.3f} ms, its adjoint {t_adj * 1e3:.3f} ms "
          f"(ratio {t_adj / t_step:.2f}; best of 20)", flush=True)

    fwd = harness.measure(plain, min_of=3, max_load=opts.max_load)
    fds = {}
    for e in FD_STEPS:
        fluid.set_state(s0)
        fluid.v[...] += e * direction
        s_plus = fluid.state()
        fluid.set_state(s0)
        fluid.v[...] -= e * direction
        s_minus = fluid.state()
        fds[e] = (plain(s_plus) - plain(s_minus)) / (2 * e)

    def gradient(checkpoints):
        def run():
            fluid.set_state(s0)
            t0 = time.perf_counter()
            r = km.diff.rollout(fluid, steps, dt, wrt=("v", "controls", "viscosity"), controls=forces,
                                checkpoints=checkpoints)
            t1 = time.perf_counter()
            ids = fluid.ids.copy()  # the rows of the final state
            g = r.backward({"x": weights[ids] / n})
            t2 = time.perf_counter()
            return {"forward": t1 - t0, "backward": t2 - t1, "g": g, "peak": r.peak_states}
        return run

    out = {}
    for label, ck in (("stored", None), ("checkpointed", int(2 * np.sqrt(steps)))):
        m = harness.measure(gradient(ck), min_of=3, max_load=opts.max_load,
                            figure=lambda v, s: v["forward"] + v["backward"])
        v = m.value
        adj = float((v["g"]["v"] * direction).sum())
        errs = {e: abs(adj - fd) / abs(fd) for e, fd in fds.items()}
        err = min(errs.values())
        ratio = v["backward"] / fwd.seconds
        out[label] = (m.seconds, adj, err)
        rec.record(f"kinema-{d}d-{label}", n, m.seconds, error=err, measurement=m,
                   notes={"steps": steps, "forward_s": f"{fwd.seconds:.4g}", "rollout_s": f"{v['forward']:.4g}",
                          "backward_s": f"{v['backward']:.4g}", "backward_over_forward": f"{ratio:.3g}",
                          "peak_states": v["peak"]})
        print(f"{d}D {label:12s} n={n} steps={steps}: forward {fwd.seconds:.3f} s (plain steps), rollout "
              f"{v['forward']:.3f} s, backward {v['backward']:.3f} s, backward/forward {ratio:.2f}, per gradient "
              f"{m.seconds:.3f} s, peak states {v['peak']}, adjoint {adj:.8g}; |adj - FD(e)|/|FD| "
              + ", ".join(f"{e:g}: {x:.1e}" for e, x in errs.items()) + f" (load {m.other_load:.2f})", flush=True)
    if opts.taichi:
        with tempfile.TemporaryDirectory() as tmp:
            arrays = Path(tmp) / "task.npz"
            np.savez(arrays, x0=x0, v0=v0, forces=forces, weights=weights, direction=direction)
            peer = Path(__file__).resolve().parent / "diff_sph_taichi_peer.py"
            for fp in ("f64", "f32"):
                res = subprocess.run([sys.executable, str(peer), str(arrays), str(dt), "--threads", str(opts.threads),
                                      "--fp", fp, "--speed-of-sound", "10", "--viscosity", "1e-4",
                                      "--spacing", str(SPACING)], capture_output=True, text=True, check=True)
                r = json.loads(res.stdout.strip().splitlines()[-1])
                err = abs(r["adjoint"] - r["fd"]) / abs(r["fd"])
                vs = abs(r["adjoint"] - out["stored"][1]) / abs(out["stored"][1])
                rec.record(f"taichi-{d}d-{fp}", n, r["gradient_seconds"], error=err,
                           notes={"steps": steps, "forward_s": f"{r['forward_seconds']:.4g}",
                                  "adjoint_vs_kinema": f"{r['adjoint']:.8g} vs {out['stored'][1]:.8g}"})
                print(f"  taichi {fp}: forward {r['forward_seconds']:.3f} s, per gradient {r['gradient_seconds']:.3f} s "
                      f"(taichi / kinema stored: {r['gradient_seconds'] / out['stored'][0]:.2f}x), adjoint "
                      f"{r['adjoint']:.8g} vs its FD {r['fd']:.8g}: {err:.1e}; vs kinema's adjoint {out['stored'][1]:.8g}: "
                      f"{vs:.1e}",
                      flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--dt", type=float, default=3e-4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--csv", type=Path, default=CSV)
    ap.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD)
    ap.add_argument("--taichi", action="store_true", help="also run the Taichi peer (needs the bench extra)")
    opts = ap.parse_args()
    km.set_num_threads(opts.threads)
    rec = harness.Recorder(opts.csv, "diff_sph_droplet", threads=opts.threads)
    print(f"commit {harness.git_commit()}, {opts.threads} threads", flush=True)
    for d in opts.dims:
        run_dim(d, opts, rec)


if __name__ == "__main__":
    main()
