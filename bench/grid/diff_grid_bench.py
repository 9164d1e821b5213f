"""Gradient cost of km.grid through km.diff: the smoke-control gradient (per-step cell
accelerations -> final density) on a 2D 256^2 and a 3D 64^3 grid, stored and checkpointed, and
side by side in one run with PhiFlow's gradient of the same 2D smoke task (PyTorch CPU backend)
and with a DiffTaichi-style Taichi tape gradient (bench/grid/diff_grid_taichi_peer.py).

    .venv/bin/python bench/grid/diff_grid_bench.py [--threads 2] [--csv bench/out/diff_grid.csv]
        [--no-phiflow] [--quick] [--taichi-only]
    .venv/bin/python bench/grid/diff_grid_bench.py --threads 2 --dims 3 --schemes maccormack bfecc --no-per-gradient

The task: a closed box of smoke (a Gaussian blob of density) at rest, T steps of dt = 0.5 h
(CFL about 0.5 once moving) each adding a random control acceleration field (one d-vector per
cell, smooth, ~1 m/s^2); loss L = <W, density_T> with a fixed random W. The gradient is dL/d(controls).

Part 1 (kinema): forward seconds (T plain steps), then rollout + backward with every state stored
and with K = 2 sqrt(T) checkpoints: backward / forward, the peak number of states held, and
the agreement |<g, r> - FD| / |FD| of the directional derivative along a random direction r with
its central difference (the benchmark refuses to record a time if it exceeds 1e-3; the
difference step 1e-5 is small so that MacCormack's clamps rarely switch inside it). Also one
step's adjoint alone against one step (C++ calls, best of 5).

Part 2 (PhiFlow 3, `phiflow` on PyPI, phi.torch.flow in float64): the same task at 64^2 and
128^2, T = 16, with semi-Lagrangian (Euler back-trace) advection on both sides and CG pressure
solves to a relative residual of 1e-10 (kinema: MGPCG). Seconds per gradient (forward + backward;
PhiFlow timed after one warm-up call that traces the graph) and each side's agreement with its
own central difference. Part 3 (Taichi, its own process): the same task with DiffTaichi's smoke
discretization (collocated grid, 50 Jacobi iterations per projection, every level on the tape),
at 64^2, 128^2 and 256^2, beside kinema at pressure tol 1e-10, 1e-6 and 1e-4 and with one
fixed V-cycle per projection (the tape's projection is not converged either). Each side's FD
agreement and the divergence its projection leaves are printed: kinema's ||div u after|| /
||div u before|| (the step's pressure.residual) and RMS divergence after; Taichi's the same,
computed in NumPy from its fields (diff_grid_taichi_peer.py), with its own divergence operator,
which equals the MAC divergence of the face averages of its collocated velocity. The summary
names the fastest kinema projection at least as good as the tape in both. The last line,
SUMMARY, holds every ratio.

    .venv/bin/python bench/grid/diff_grid_bench.py --vcycles 1 2 4 [--threads 1]

runs only Part 3, kinema with the fixed V-cycle projection (pressure_vcycles = 1, 2, 4: a
linear map whose adjoint is exact, like the tape's fixed Jacobi sweeps) beside tol 1e-10 and
the tape, with the divergence each kinema projection leaves (mean pressure.residual).
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

CSV = Path(__file__).resolve().parents[1] / "out" / "diff_grid.csv"
TOL = 1e-10  # relative residual of every pressure solve, both sides


def smooth_field(rng, shape, d, scale=1.0):
    """A smooth random vector field (a few Fourier modes) on the cells of `shape`, (*shape, d)."""
    x = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) / n for n in shape], indexing="ij"), -1)
    out = np.zeros(shape + (d,))
    for _ in range(4):
        k = rng.normal(0, 6, d)
        out += rng.normal(0, scale / 2, d) * np.sin(x @ k + rng.uniform(0, 2 * np.pi))[..., None]
    return out


def task(shape, steps, seed=0):
    rng = np.random.default_rng(seed)
    d = len(shape)
    h = 1.0 / shape[0]
    c = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) * h for n in shape], indexing="ij"), -1)
    centre = np.array([0.5, 0.3, 0.5][:d])
    rho0 = np.exp(-np.sum((c - centre) ** 2, -1) / 0.01)
    controls = np.stack([smooth_field(rng, shape, d) for _ in range(steps)])
    weights = rng.normal(size=shape)
    direction = rng.normal(size=controls.shape)
    return h, 0.5 * h, rho0, controls, weights, direction


def kinema_fluid(shape, h, rho0, advection, rk_order, tol, vcycles=None):
    sim = km.grid.Fluid(shape, h, advection=advection, rk_order=rk_order, tol=tol, density=True,
                        pressure_vcycles=vcycles)
    sim.density = rho0
    return sim


def kinema_part(rec, shape, steps, advection, rk_order, opts, tol=TOL, one_step=True, vcycles=None):
    h, dt, rho0, controls, weights, direction = task(shape, steps)
    sim = kinema_fluid(shape, h, rho0, advection, rk_order, tol, vcycles)
    s0 = sim.state()
    label = f"{len(shape)}D {'x'.join(map(str, shape))} {advection} rk{rk_order} T={steps}"
    if vcycles:
        label += f" vcycles={vcycles}"
    elif tol != TOL:
        label += f" tol={tol:g}"

    def loss(c):
        sim.set_state(s0)
        for k in range(steps):
            sim._diff_step(dt, c[k], {})
        return float(np.sum(weights * sim.density))

    def plain():
        return loss(controls)

    fwd = harness.measure(plain, min_of=3, max_load=opts.max_load)
    e = 1e-5  # small enough that MacCormack's clamps rarely switch within the difference
    fd = (loss(controls + e * direction) - loss(controls - e * direction)) / (2 * e)

    def gradient(checkpoints):
        def run():
            sim.set_state(s0)
            t0 = time.perf_counter()
            r = km.diff.rollout(sim, steps, dt, wrt=("controls",), controls=controls, checkpoints=checkpoints)
            t1 = time.perf_counter()
            g = r.backward({"density": weights})["controls"]
            t2 = time.perf_counter()
            return {"forward": t1 - t0, "backward": t2 - t1, "g": g, "peak": r.peak_states}
        return run

    out = {}
    for name, ck in (("stored", None), ("checkpointed", int(2 * np.sqrt(steps)))):
        m = harness.measure(gradient(ck), min_of=2, max_load=opts.max_load,
                            figure=lambda v, s: v["forward"] + v["backward"])
        v = m.value
        err = abs(float(np.sum(v["g"] * direction)) - fd) / abs(fd)
        if err > 1e-3:
            raise SystemExit(f"{label} {name}: the gradient disagrees with its central difference ({err:.2e})")
        ratio = v["backward"] / fwd.seconds
        rec.record(f"kinema-{name}-{advection}-rk{rk_order}", shape, m.seconds, error=err, measurement=m,
                   notes={"steps": steps, "tol": tol, "vcycles": vcycles or "", "forward_s": f"{fwd.seconds:.4g}", "backward_s": f"{v['backward']:.4g}",
                          "backward_over_forward": f"{ratio:.3g}", "peak_states": v["peak"],
                          "checkpoints": ck or "all"})
        print(f"kinema {label} {name:12s}: forward {fwd.seconds:.3f} s, rollout {v['forward']:.3f} s, backward "
              f"{v['backward']:.3f} s, backward/forward {ratio:.2f}, per gradient {m.seconds:.3f} s, peak states "
              f"{v['peak']} (K={ck or 'all'}, 3 sqrt(T) = {3 * np.sqrt(steps):.1f}), |adj - FD|/|FD| {err:.1e} "
              f"(load {m.other_load:.2f}{', disturbed' if m.disturbed else ''})", flush=True)
        out[name] = (m, err, ratio)
    if not one_step:
        return out
    # one step and its adjoint alone, from the state after a few steps (at rest, the velocity
    # advection's adjoint has no back-trace term and costs far less)
    sim.set_state(s0)
    for k in range(min(4, steps - 1)):
        sim._diff_step(dt, controls[k], {})
    s_mid = sim.state()
    sim._diff_step(dt, controls[0], {})
    s1 = sim.state()
    # a dense gradient in every field, as the steps before the last see it (a zero field's
    # advection adjoint is skipped)
    grad_rng = np.random.default_rng(1)
    grads = {n: grad_rng.normal(size=s1[n].shape) for n in sim._diff_state_names}

    def best_of(fn, reps=5):
        return harness.best_of(fn, reps)

    def one_step():
        sim.set_state(s_mid)
        sim._diff_step(dt, controls[0], {})

    t_step = best_of(one_step)
    t_adj = best_of(lambda: sim._diff_step_adjoint(dt, s_mid, s1, controls[0], grads, {}))
    rec.record(f"kinema-one-step-adjoint-{advection}-rk{rk_order}", shape, t_adj,
               notes={"step_s": f"{t_step:.4g}", "ratio": f"{t_adj / t_step:.3g}"})
    print(f"kinema {label}: one step {t_step * 1e3:.1f} ms (with set_state), its adjoint {t_adj * 1e3:.1f} ms "
          f"(ratio {t_adj / t_step:.2f}; best of 5)", flush=True)
    return out


def phiflow_part(rec, n, steps, opts):
    import torch
    from phi.torch.flow import (Box, CenteredGrid, Solve, StaggeredGrid, ZERO_GRADIENT, advect, batch, channel,
                                fluid, math, resample, spatial)
    torch.set_num_threads(opts.threads)
    math.set_global_precision(64)
    shape = (n, n)
    h, dt, rho0, controls, weights, direction = task(shape, steps)
    bounds = Box(x=1, y=1)
    smoke0 = CenteredGrid(math.tensor(rho0, spatial("x,y")), ZERO_GRADIENT, x=n, y=n, bounds=bounds)
    vel0 = StaggeredGrid(0, 0, x=n, y=n, bounds=bounds)
    W = math.tensor(weights, spatial("x,y"))

    def loss(ctrl):
        smoke, v = smoke0, vel0
        for k in range(steps):
            c = CenteredGrid(ctrl.time[k], 0, x=n, y=n, bounds=bounds)
            smoke = advect.semi_lagrangian(smoke, v, dt)
            v = advect.semi_lagrangian(v, v, dt) + dt * resample(c, to=v)
            v, _ = fluid.make_incompressible(v, (), Solve("CG", TOL, 0, max_iterations=10 * n * n))
        return math.sum(smoke.values * W, spatial)

    def as_tensor(c):
        return math.tensor(c, batch("time"), spatial("x,y"), channel(vector="x,y"))

    grad = math.gradient(loss, "ctrl", get_output=True)
    t0 = time.perf_counter()
    grad(as_tensor(controls))  # traces the graph
    first = time.perf_counter() - t0

    def run():
        _, g = grad(as_tensor(controls))
        return g.numpy("time,x,y,vector")

    m = harness.measure(run, min_of=2, max_load=opts.max_load)
    e = 1e-4
    fd = (float(loss(as_tensor(controls + e * direction))) - float(loss(as_tensor(controls - e * direction)))) / (2 * e)
    err = abs(float(np.sum(m.value * direction)) - fd) / abs(fd)
    rec.record("phiflow-torch-f64", shape, m.seconds, error=err, measurement=m,
               notes={"steps": steps, "first_call_s": f"{first:.3g}"})
    print(f"PhiFlow {n}x{n} T={steps}: per gradient {m.seconds:.3f} s (first call {first:.2f} s), "
          f"|adj - FD|/|FD| {err:.1e} (load {m.other_load:.2f}{', disturbed' if m.disturbed else ''})", flush=True)
    return m.seconds, err


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--csv", type=Path, default=CSV)
    ap.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD)
    ap.add_argument("--no-phiflow", action="store_true", help="skip PhiFlow (minutes per gradient at 128^2)")
    ap.add_argument("--no-taichi", action="store_true")
    ap.add_argument("--quick", action="store_true", help="small sizes (a check that the script runs)")
    ap.add_argument("--taichi-only", action="store_true",
                    help="only the per-gradient comparison (kinema beside Taichi and PhiFlow), no backward/forward cases")
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 3], help="the backward/forward cases' dimensions")
    ap.add_argument("--schemes", nargs="+", default=["semi_lagrangian", "maccormack", "bfecc"],
                    help="the backward/forward cases' advection schemes")
    ap.add_argument("--no-per-gradient", action="store_true",
                    help="only the backward/forward cases (no per-gradient comparison with Taichi and PhiFlow)")
    ap.add_argument("--vcycles", type=int, nargs="+",
                    help="only the Taichi comparison, kinema with pressure_vcycles = each of these")
    opts = ap.parse_args()
    km.set_num_threads(opts.threads)
    rec = harness.Recorder(opts.csv, "diff_grid", threads=opts.threads)
    print(f"threads {opts.threads}, commit {rec.commit}", flush=True)
    if opts.vcycles:
        vcycle_comparison(rec, opts)
        return
    big2, big3, steps2, steps3 = ((256, 256), (64, 64, 64), 16, 9) if not opts.quick else ((32, 32), (12, 12, 12), 4, 4)
    summary = []
    cases = ((big2, steps2, "semi_lagrangian", 1), (big2, steps2, "maccormack", 2), (big2, steps2, "bfecc", 2),
             (big3, steps3, "semi_lagrangian", 1), (big3, steps3, "maccormack", 2), (big3, steps3, "bfecc", 2))
    for shape, steps, advection, rk in cases if not opts.taichi_only else ():
        if len(shape) not in opts.dims or advection not in opts.schemes:
            continue
        res = kinema_part(rec, shape, steps, advection, rk, opts)
        summary.append(f"{len(shape)}D {shape[0]}^{len(shape)} {advection} bwd/fwd {res['stored'][2]:.2f} stored, "
                       f"{res['checkpointed'][2]:.2f} checkpointed")
    for n in ((64, 128, 256) if not opts.quick else (16,)) if not opts.no_per_gradient else ():
        steps = 16 if not opts.quick else 4
        # kinema's projections: solved to a tolerance (1e-10; 1e-6 and 1e-4: looser, 4 MGPCG
        # iterations at 1e-4) and one fixed V-cycle (the cheapest, still more divergence-free
        # than the tape's 50 Jacobi sweeps): seconds, FD agreement, divergence left
        rows = []
        for name, tol, vc in (("tol 1e-10", TOL, None), ("tol 1e-6", 1e-6, None), ("tol 1e-4", 1e-4, None),
                              ("1 V-cycle", TOL, 1)):
            res = kinema_part(rec, (n, n), steps, "semi_lagrangian", 1, opts, tol=tol, one_step=tol == TOL and not vc,
                              vcycles=vc)
            left, rms = divergence_left((n, n), steps, tol=tol, vcycles=vc)
            print(f"kinema {n}x{n} {name}: divergence left {left:.1e} (RMS div after {rms:.1e} 1/s)", flush=True)
            rows.append((name, res["stored"][0].seconds, res["stored"][1], left, rms))
        t_km, err_km = rows[0][1], rows[0][2]
        if not opts.no_phiflow and n <= 128:  # PhiFlow: minutes per gradient at 128^2
            t_phi, err_phi = phiflow_part(rec, n, steps, opts)
            print(f"=> {n}x{n}: kinema {t_km:.3f} s per gradient (|adj - FD|/|FD| {err_km:.1e}) vs PhiFlow "
                  f"{t_phi:.3f} s ({err_phi:.1e}): {t_phi / t_km:.1f}x", flush=True)
            summary.append(f"{n}^2 PhiFlow/kinema {t_phi / t_km:.1f}x (FD {err_phi:.1e} vs {err_km:.1e})")
        if not opts.no_taichi:
            t_ti, err_ti, ti = taichi_part(rec, n, steps, opts)
            parts = []
            for name, t, err, left, rms in rows:
                print(f"=> {n}x{n}: kinema {name} {t:.3f} s (FD {err:.1e}, div left {left:.1e}) vs Taichi "
                      f"{t_ti:.3f} s (FD {err_ti:.1e}, div left {ti['div_left']:.2f}, {ti['jacobi']} Jacobi "
                      f"iterations per projection): {t_ti / t:.1f}x", flush=True)
                parts.append(f"{name} {t_ti / t:.1f}x (FD {err:.0e}, div left {left:.0e})")
            # the fastest kinema projection at least as good as the tape in both FD agreement and
            # the divergence it leaves
            fair = [(t, name) for name, t, err, left, _ in rows if err <= err_ti and left <= ti["div_left"]]
            best = f"; at equal or better FD agreement and divergence {t_ti / min(fair)[0]:.1f}x ({min(fair)[1]})" if fair else ""
            summary.append(f"{n}^2 Taichi/kinema (Taichi FD {err_ti:.0e}, div left {ti['div_left']:.2f}, "
                           f"{ti['div_left_exact_solve']:.2f} if solved exactly): "
                           + ", ".join(parts) + best)
    print("SUMMARY: " + "; ".join(summary), flush=True)

def divergence_left(shape, steps, tol=TOL, vcycles=None):
    """Means over the task's T projections of ||div u after|| / ||div u before|| (the step's
    pressure.residual) and of the RMS divergence after [1/s] (Fluid.divergence)."""
    h, dt, rho0, controls, _, _ = task(shape, steps)
    sim = kinema_fluid(shape, h, rho0, "semi_lagrangian", 1, tol, vcycles)
    left, rms = [], []
    for k in range(steps):
        left.append(sim._core.step(dt, controls[k]).pressure.residual)
        rms.append(np.sqrt(np.mean(sim.divergence() ** 2)))
    return float(np.mean(left)), float(np.mean(rms))


def vcycle_comparison(rec, opts):
    """The Taichi task with kinema's fixed V-cycle projection (pressure_vcycles) beside the
    converged one (tol 1e-10) and the tape; the summary gives Taichi/kinema per gradient for the
    fewest cycles whose FD agreement is at least the tape's, and the divergence each leaves."""
    summary = []
    steps = 16 if not opts.quick else 4
    for n in ((64, 128, 256) if not opts.quick else (16, 32)):
        rows = []
        for vc in [None] + list(opts.vcycles):
            r = kinema_part(rec, (n, n), steps, "semi_lagrangian", 1, opts, one_step=False, vcycles=vc)
            m, err, _ = r["stored"]
            rows.append((vc, m.seconds, err, divergence_left((n, n), steps, vcycles=vc)[0]))
        t_ti, err_ti, ti = taichi_part(rec, n, steps, opts)
        jacobi = ti["jacobi"]
        parts = []
        for vc, t, err, div in rows:
            name = f"{vc} V-cycles" if vc else "tol 1e-10"
            print(f"=> {n}x{n}: kinema {name}: {t:.3f} s per gradient, FD {err:.1e}, divergence left {div:.1e}; "
                  f"Taichi ({jacobi} Jacobi) {t_ti:.3f} s, FD {err_ti:.1e}: Taichi/kinema {t_ti / t:.1f}x", flush=True)
            parts.append(f"{name} {t_ti / t:.1f}x (FD {err:.0e}, div left {div:.0e})")
        summary.append(f"{n}^2 Taichi/kinema (Taichi FD {err_ti:.0e}, div left {ti['div_left']:.2f}): " + ", ".join(parts))
    print("SUMMARY: " + "; ".join(summary), flush=True)


def taichi_part(rec, n, steps, opts):
    """DiffTaichi-style smoke gradient on Taichi's CPU backend, in its own process."""
    h, dt, rho0, controls, weights, direction = task((n, n), steps)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "task.npz"
        np.savez(path, rho0=rho0, controls=controls, weights=weights, direction=direction, h=h, dt=dt)
        peer = Path(__file__).resolve().parent / "diff_grid_taichi_peer.py"
        before = harness.sample_cpu()
        out = subprocess.run([sys.executable, str(peer), str(path), "--threads", str(opts.threads)],
                             capture_output=True, text=True, check=True)
        load = harness.other_load(before, harness.sample_cpu())
    res = json.loads(out.stdout.strip().splitlines()[-1])
    err = abs(res["adjoint"] - res["fd"]) / abs(res["fd"])
    rec.record("taichi-tape-f64", (n, n), res["gradient_seconds"], error=err,
               notes={"steps": steps, "jacobi": res["jacobi"], "process_other_load": f"{load:.2f}",
                      "div_left": f"{res['div_left']:.3g}", "div_after_rms": f"{res['div_after_rms']:.3g}",
                      "poisson_residual": f"{res['poisson_residual']:.3g}",
                      "div_left_exact_solve": f"{res['div_left_exact_solve']:.3g}"})
    print(f"Taichi {n}x{n} T={steps}: per gradient {res['gradient_seconds']:.3f} s, |adj - FD|/|FD| {err:.1e} "
          f"(Jacobi {res['jacobi']}; other load over its process {load:.2f}); divergence left "
          f"{res['div_left']:.2f} (RMS before {res['div_before_rms']:.2e}, after {res['div_after_rms']:.2e} 1/s), "
          f"Jacobi relative residual {res['poisson_residual']:.2f}; its discretization with the Poisson equation solved "
          f"exactly would leave {res['div_left_exact_solve']:.2f}", flush=True)
    return res["gradient_seconds"], err, res


if __name__ == "__main__":
    main()
