"""km.mpm benchmarks (results in bench/out/mpm.csv; summary in bench/RESULTS.md, "MPM").

    .venv/bin/python bench/mpm/mpm_bench.py scaling   [--threads 2]   # 3D step time, 1e4..1e6 particles
    .venv/bin/python bench/mpm/mpm_bench.py precision                 # dam-break front error vs wall time
    .venv/bin/python bench/mpm/mpm_bench.py taichi    [--threads 2] [--repeat 3] [--fixed-team]   # beside Taichi's mpm88 / mpm128 / mpm3d

scaling: 3D water and sand blocks of 1e4, 1e5 and 1e6 particles (8 per cell) in a 128^3 domain,
mean time per step over 5 steps after 2 warm-up steps, with the per-stage times (sort, P2G,
grid, G2P) the solver reports.
precision: the 2D Martin-Moyce dam break (tests/test_mpm.py) at 8, 16, 32, 64 cells per column
width: mean relative error of the surge front for T in [1.2, 2.6] against the experiment as
published, against it with one gate delay dT fitted to the finest run (the experiment's gate
removal delays its front), and against the finest run (self-convergence), vs wall time.
taichi: Taichi's shipped mpm88, mpm128 and mpm3d examples run headless on its CPU backend
(bench/mpm/mpm_taichi_peer.py; float32 as shipped) and kinema (float64) from the example's own
initial state, same particles, grid and dt; seconds per substep (wall and CPU), best of 3 blocks,
run back to back in one run. Each pair's mean particle position after the run must agree (a fast
wrong answer fails).
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

STAT_FIELDS = ("sort_seconds", "p2g_seconds", "grid_seconds", "g2p_seconds", "active_blocks")

OUT = Path(__file__).resolve().parents[1] / "out"
CSV = OUT / "mpm.csv"


def scaling(opts):
    rec = harness.Recorder(CSV, "mpm3d_step", threads=opts.threads)
    km.set_num_threads(opts.threads)
    for material in ("water", "sand"):
        for n in (10_000, 100_000, 1_000_000):
            # a cube of n particles at 2 per cell per axis, resting on the floor of a 128^3 domain
            shape = 128
            h = 1.0 / shape
            side = round((n / 8) ** (1 / 3))
            sim = km.mpm.Simulation((shape,) * 3, h, gravity=[0, -9.81, 0], boundary="slip")
            lo = np.array([0.5 - side * h / 2, 2 * h, 0.5 - side * h / 2])
            x = km.mpm.block(lo, lo + side * h, h / 2)
            kw = {"friction_angle": 30.0} if material == "sand" else {"youngs_modulus": 1e5}
            sim.add_particles(x, material, density=1000.0, volume=(h / 2) ** 3, **kw)
            dt = sim.stable_dt(0.5)
            for _ in range(2):
                sim.step(dt)

            def run():
                cpu = time.process_time()
                stats = [sim.step(dt) for _ in range(5)]
                out = {k: float(np.mean([getattr(s, k) for s in stats])) for k in STAT_FIELDS}
                out["cpu_seconds"] = (time.process_time() - cpu) / 5
                return out

            m = harness.measure(run, min_of=2, max_tries=4, max_load=opts.max_load)
            st = m.value
            assert np.isfinite(sim.x).all()
            rec.record(f"kinema-{material}", len(x), m.seconds / 5, measurement=m,
                       notes={k: f"{st[k]:.4g}" for k in ("cpu_seconds", "sort_seconds", "p2g_seconds",
                                                           "grid_seconds", "g2p_seconds", "active_blocks")})
            print(f"{material:6s} n={len(x):8d} step {m.seconds / 5 * 1e3:9.2f} ms (cpu {st['cpu_seconds'] * 1e3:9.2f})  sort {st['sort_seconds']*1e3:7.2f}"
                  f"  p2g {st['p2g_seconds']*1e3:8.2f}  grid {st['grid_seconds']*1e3:7.2f}"
                  f"  g2p {st['g2p_seconds']*1e3:8.2f}  blocks {st['active_blocks']:.0f}  load {m.other_load:.2f}",
                  flush=True)
    # The sparse grid: a small body in a 256^3 domain costs what it costs in a 64^3 one.
    for shape in (64, 256):
        h = 1.0 / shape
        sim = km.mpm.Simulation((shape,) * 3, h, gravity=[0, -9.81, 0])
        x = km.mpm.block([0.45] * 3, [0.45 + 16 * h] * 3, h / 2)
        sim.add_particles(x, "water", density=1000.0, youngs_modulus=1e5, volume=(h / 2) ** 3)
        dt = sim.stable_dt(0.5)
        sim.step(dt)
        m = harness.measure(lambda: [sim.step(dt) for _ in range(20)], min_of=3, max_load=opts.max_load)
        rec.record("kinema-water-small-body", f"{shape}^3 grid, {len(x)} particles", m.seconds / 20, measurement=m)
        print(f"small body ({len(x)} particles) in {shape}^3: {m.seconds / 20 * 1e3:.3f} ms/step", flush=True)


def precision(opts):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from test_mpm import _dam_break_front

    rec = harness.Recorder(CSV, "mpm2d_dam_break_front", threads=opts.threads)
    km.set_num_threads(opts.threads)
    ref = km.sph.martin_moyce()
    ref = ref[(ref[:, 0] >= 1.2) & (ref[:, 0] <= 2.6)]
    runs = {}
    for cells in (8, 16, 32, 64):
        m = harness.measure(lambda: _dam_break_front(cells), min_of=1, max_load=opts.max_load)
        runs[cells] = m
    finest = max(runs)
    T_f, Z_f = runs[finest].value
    # The experiment's front lags any inviscid run by the gate's removal: one delay dT, fitted
    # to the finest run (least squares over the compared window), is applied to every run.
    shifts = np.linspace(0.0, 0.6, 601)
    misfit = [np.mean((np.interp(ref[:, 0] - d, T_f, Z_f) / ref[:, 1] - 1) ** 2) for d in shifts]
    delay = float(shifts[int(np.argmin(misfit))])
    print(f"gate delay fitted to the {finest}-cell run: dT = {delay:.3f}", flush=True)
    for cells, m in runs.items():
        T, Z = m.value
        err = float(np.mean(np.abs(np.interp(ref[:, 0], T, Z) - ref[:, 1]) / ref[:, 1]))
        err_delay = float(np.mean(np.abs(np.interp(ref[:, 0] - delay, T, Z) - ref[:, 1]) / ref[:, 1]))
        Tc = ref[:, 0]
        self_err = float(np.mean(np.abs(np.interp(Tc, T, Z) - np.interp(Tc, T_f, Z_f)) / np.interp(Tc, T_f, Z_f)))
        rec.record("kinema-water", f"{cells} cells/width", m.seconds, error=err, measurement=m,
                   notes={"error_with_gate_delay": f"{err_delay:.4g}", "gate_delay": f"{delay:.3f}",
                          "difference_to_finest": f"{self_err:.4g}" if cells != finest else "-"})
        print(f"dam break {cells:3d} cells per width: {m.seconds:7.2f} s, front error {err:.3f} "
              f"(with the gate delay {err_delay:.3f}), against the {finest}-cell run "
              f"{self_err if cells != finest else float('nan'):.4f}", flush=True)


def kinema_scene(kind, start, adapt_threads=True):
    """kinema's version of Taichi's example `kind` from the example's own initial state."""
    # The examples hold the velocities of the nodes within 3 cells of the box's sides
    # (separate); kinema holds the nodes at and beyond its walls, so its domain is the same
    # grid less two cells on each side.
    x, v, n_grid = start["x"], start["v"], int(start["n_grid"])
    d = x.shape[1]
    h = 1.0 / n_grid
    vol = (0.5 * h) ** d  # the dynamics depend on density only (mass and stress both scale with it)
    gravity = start["gravity"] if kind == "mpm128" else [0, -9.8] + [0] * (d - 2)
    sim = km.mpm.Simulation((n_grid - 4,) * d, h, gravity=gravity, boundary="separate", origin=[2 * h] * d,
                            adapt_threads=adapt_threads)
    if kind == "mpm128":
        # material 0 water (mu = 0, lambda = lambda_0: tau = lambda_0 J (J - 1) I, kinema's Tait
        # water with K = lambda_0 to first order), 1 jelly (E 0.3 * 5e3), 2 snow (E 5e3, hardening).
        E, nu = 5e3, 0.2
        lam = E * nu / ((1 + nu) * (1 - 2 * nu))
        mat = start["material"]
        for code, material, e in ((0, "water", lam), (1, "elastic", 0.3 * E), (2, "snow", E)):
            rows = mat == code
            sim.add_particles(x[rows], material, density=1.0, youngs_modulus=e,
                              poisson_ratio=None if material == "water" else nu, velocity=v[rows], volume=vol)
    else:
        # mpm88 / mpm3d: tau = E (J - 1) I with E = 400; kinema's Tait water with K = 400.
        sim.add_particles(x, "water", density=1.0, youngs_modulus=400.0, velocity=v, volume=vol)
    return sim


def taichi(opts):
    rec = harness.Recorder(CSV, "mpm_vs_taichi", threads=opts.threads)
    km.set_num_threads(opts.threads)
    steps = opts.steps
    summary, ratios = [], {}
    for kind in ("mpm88", "mpm128", "mpm3d") * opts.repeat:
        with tempfile.TemporaryDirectory() as tmp:
            start_file = Path(tmp) / "start.npz"
            peer = subprocess.run([sys.executable, str(Path(__file__).with_name("mpm_taichi_peer.py")), kind,
                                   str(steps), str(start_file), "--threads", str(opts.threads)],
                                  capture_output=True, text=True)
            if peer.returncode != 0:
                raise SystemExit(f"{kind}: the Taichi peer failed:\n{peer.stderr[-2000:]}")
            ti_res = json.loads(peer.stdout.strip().splitlines()[-1])
            start = dict(np.load(start_file))
        dt = float(start["dt"])
        x0, n_grid = start["x"], int(start["n_grid"])
        sim = kinema_scene(kind, start, adapt_threads=not opts.fixed_team)
        for _ in range(steps):
            sim.step(dt)

        def block():
            t0, c0 = time.perf_counter(), time.process_time()
            stats = [sim.step(dt) for _ in range(steps)]
            return (time.perf_counter() - t0) / steps, (time.process_time() - c0) / steps, stats

        m = harness.measure(block, min_of=3, max_tries=6, figure=lambda v, wall: v[0], max_load=opts.max_load)
        cpu, stats = m.value[1], m.value[2]
        # kinema's per-stage split (median StepStats of the best block) [ms]
        stages = {k: 1e3 * float(np.median([getattr(s, k + "_seconds") for s in stats]))
                  for k in ("sort", "p2g", "grid", "g2p")}
        stages["step"] = 1e3 * float(np.median([s.seconds for s in stats]))
        one_thread = float(np.mean([s.threads == 1 for s in stats]))
        # Both run 4 * steps substeps from the same start; their mean positions must agree to
        # within the f32 rounding and the differing equations of state (well below a cell).
        check = kinema_scene(kind, start)
        for _ in range(ti_res["total_steps"]):
            check.step(dt)
        drift = float(np.abs(check.x.mean(axis=0) - np.array(ti_res["mean"])).max())
        ok = ti_res["finite"] and np.isfinite(check.x).all() and drift < 1.0 / n_grid
        speedup = ti_res["seconds"] / m.seconds
        case = f"{kind} {len(x0)}p {n_grid}^{x0.shape[1]} dt {dt:g}"
        rec.record("taichi-f32", case, ti_res["seconds"], notes={"cpu_seconds": f"{ti_res['cpu_seconds']:.4g}",
                                                                "source": ti_res["file"]})
        rec.record("kinema-f64", case, m.seconds, measurement=m, error=drift,
                   notes={"speedup": f"{speedup:.2f}", "cpu_seconds": f"{cpu:.4g}", "check": "ok" if ok else "FAILED",
                          "one_thread_steps": f"{one_thread:.2f}", "adapt_threads": str(not opts.fixed_team),
                          **{f"{k}_ms": f"{v:.4g}" for k, v in stages.items()}})
        print(f"{case}: taichi {ti_res['seconds'] * 1e3:.3f} ms/substep (cpu {ti_res['cpu_seconds'] * 1e3:.3f}), "
              f"kinema {m.seconds * 1e3:.3f} ms/substep (cpu {cpu * 1e3:.3f}): {speedup:.2f}x wall, "
              f"{ti_res['cpu_seconds'] / cpu:.2f}x cpu; mean-position difference {drift:.2e} "
              f"({'ok' if ok else 'FAILED'}), other load {m.other_load:.2f}; kinema steps on one thread "
              f"{100 * one_thread:.0f}%; kinema stages [ms, median]: "
              + " / ".join(f"{k} {v:.3f}" for k, v in stages.items()), flush=True)
        if not ok:
            raise SystemExit(f"{kind}: kinema and Taichi disagree ({drift:.3g}); no time recorded as valid")
        summary.append(f"{kind} {speedup:.2f}x (cpu {ti_res['cpu_seconds'] / cpu:.2f}x, load {m.other_load:.2f})")
        ratios.setdefault(kind, []).append(speedup)
    print(f"summary, Taichi / kinema time per substep, {opts.threads} thread(s), target >= 2x: " + "; ".join(summary),
          flush=True)
    if opts.repeat > 1:
        print(f"spread over {opts.repeat} runs (median [min, max]): " + "; ".join(
            f"{k} {np.median(r):.2f}x [{min(r):.2f}, {max(r):.2f}]" for k, r in ratios.items()), flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["scaling", "precision", "taichi"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=1, help="taichi: run the three comparisons this many times")
    ap.add_argument("--fixed-team", action="store_true",
                    help="taichi: kinema always uses --threads threads (adapt_threads=False)")
    ap.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD,
                    help="other processes' load (cores) above which a run counts as disturbed and is retried")
    opts = ap.parse_args()
    {"scaling": scaling, "precision": precision, "taichi": taichi}[opts.what](opts)


if __name__ == "__main__":
    main()
