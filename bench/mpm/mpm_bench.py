"""km.mpm benchmarks (results in bench/out/mpm.csv; summary in bench/RESULTS.md, "MPM").

    .venv/bin/python bench/mpm/mpm_bench.py scaling   [--threads 2]   # 3D step time, 1e4..1e6 particles
    .venv/bin/python bench/mpm/mpm_bench.py precision                 # dam-break front error vs wall time
    .venv/bin/python bench/mpm/mpm_bench.py taichi    [--threads 2]   # side by side with Taichi (CPU, f32)

scaling: 3D water and sand blocks of 1e4, 1e5 and 1e6 particles (8 per cell) in a 128^3 domain,
mean time per step over 5 steps after 2 warm-up steps, with the per-stage times (sort, P2G,
grid, G2P) the solver reports.
precision: the 2D Martin-Moyce dam break (tests/test_mpm.py) at 8, 16, 32 cells per column width:
mean relative error of the surge front against the experiment for T in [1.2, 2.6] vs wall time.
taichi: the three scenes of Taichi's mpm88, mpm99 and mpm3d examples (particle counts, grids and
dt of the examples) from the same initial positions; kinema float64 vs Taichi float32, seconds per
substep, best of 3 blocks. Each pair's mean particle position after the run must agree (a fast
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
            sim = km.mpm.Simulation((shape,) * 3, h, boundary="slip")
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
                out = {k: float(np.mean([s[k] for s in stats])) for k in stats[0]}
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
        sim = km.mpm.Simulation((shape,) * 3, h)
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
    for cells in (8, 16, 32):
        m = harness.measure(lambda: _dam_break_front(cells), min_of=1, max_load=opts.max_load)
        T, Z = m.value
        err = float(np.mean(np.abs(np.interp(ref[:, 0], T, Z) - ref[:, 1]) / ref[:, 1]))
        rec.record("kinema-water", f"{cells} cells/width", m.seconds, error=err, measurement=m)
        print(f"dam break {cells:3d} cells per width: {m.seconds:7.2f} s, front error {err:.3f}", flush=True)


def scene(kind, rng):
    """Initial positions, grid and dt of Taichi's example `kind`."""
    if kind == "mpm88":
        return rng.random((8192, 2)) * 0.4 + 0.2, 128, 2e-4
    if kind == "mpm99":
        # three squares (water, jelly, snow) of 3000 particles each
        x = np.concatenate([rng.random((3000, 2)) * 0.2 + [0.3 + 0.1 * i, 0.05 + 0.32 * i] for i in range(3)])
        return x, 128, 1e-4
    return rng.random((8192, 3)) * 0.4 + 0.15, 32, 4e-4


def kinema_scene(kind, x, n_grid, dt):
    # The examples hold the velocities of the nodes within 3 cells of the box's sides
    # (separate); kinema holds the nodes at and beyond its walls, so its domain is the same
    # grid less two cells on each side.
    d = x.shape[1]
    h = 1.0 / n_grid
    vol = (0.5 * h) ** d
    sim = km.mpm.Simulation((n_grid - 4,) * d, h, gravity=[0, -9.8] + [0] * (d - 2), boundary="separate",
                            origin=[2 * h] * d)
    if kind == "mpm99":
        E, nu = 5e3, 0.2
        third = len(x) // 3
        sim.add_particles(x[:third], "water", density=1.0, youngs_modulus=E, volume=vol)
        sim.add_particles(x[third:2 * third], "elastic", density=1.0, youngs_modulus=0.3 * E, poisson_ratio=nu,
                          volume=vol)
        sim.add_particles(x[2 * third:], "snow", density=1.0, youngs_modulus=E, poisson_ratio=nu, volume=vol)
    else:
        sim.add_particles(x, "water", density=1.0, youngs_modulus=400.0, volume=vol)
    return sim


def taichi(opts):
    rec = harness.Recorder(CSV, "mpm_vs_taichi", threads=opts.threads)
    km.set_num_threads(opts.threads)
    rng = np.random.default_rng(0)
    steps = opts.steps
    for kind in ("mpm88", "mpm99", "mpm3d"):
        x0, n_grid, dt = scene(kind, rng)
        with tempfile.NamedTemporaryFile(suffix=".npy", delete=False) as f:
            np.save(f, x0)
        peer = subprocess.run([sys.executable, str(Path(__file__).with_name("mpm_taichi_peer.py")), kind, f.name,
                               str(steps), str(dt), str(n_grid), "--threads", str(opts.threads)],
                              capture_output=True, text=True, check=True)
        ti_res = json.loads(peer.stdout.strip().splitlines()[-1])
        sim = kinema_scene(kind, x0, n_grid, dt)
        for _ in range(steps):
            sim.step(dt)

        def block():
            start, cpu = time.perf_counter(), time.process_time()
            for _ in range(steps):
                sim.step(dt)
            return (time.perf_counter() - start) / steps, (time.process_time() - cpu) / steps

        m = harness.measure(block, min_of=3, max_tries=6, figure=lambda v, wall: v[0], max_load=opts.max_load)
        cpu = m.value[1]
        # Both run 4 * steps substeps from the same start; their mean positions must agree to
        # within the f32 rounding and the differing equation of state (well below a cell).
        check = kinema_scene(kind, x0, n_grid, dt)
        for _ in range(ti_res["total_steps"]):
            check.step(dt)
        mean_k = check.x.mean(axis=0)
        drift = float(np.abs(mean_k - np.array(ti_res["mean"])).max())
        ok = ti_res["finite"] and np.isfinite(check.x).all() and drift < 1.0 / n_grid
        speedup = ti_res["seconds"] / m.seconds
        rec.record("taichi-f32", f"{kind} {len(x0)}p {n_grid}^{x0.shape[1]}", ti_res["seconds"],
                   notes={"cpu_seconds": f"{ti_res['cpu_seconds']:.4g}"})
        rec.record("kinema-f64", f"{kind} {len(x0)}p {n_grid}^{x0.shape[1]}", m.seconds, measurement=m,
                   error=drift, notes={"speedup": f"{speedup:.2f}", "cpu_seconds": f"{cpu:.4g}",
                                       "check": "ok" if ok else "FAILED"})
        print(f"{kind}: taichi {ti_res['seconds'] * 1e3:.3f} ms/substep (cpu {ti_res['cpu_seconds'] * 1e3:.3f}), "
              f"kinema {m.seconds * 1e3:.3f} ms/substep (cpu {cpu * 1e3:.3f}): {speedup:.2f}x wall, "
              f"{ti_res['cpu_seconds'] / cpu:.2f}x cpu; mean-position difference {drift:.2e} "
              f"({'ok' if ok else 'FAILED'}), load {m.other_load:.2f}", flush=True)
        if not ok:
            raise SystemExit(f"{kind}: kinema and Taichi disagree ({drift:.3g}); no time recorded as valid")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["scaling", "precision", "taichi"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD,
                    help="other processes' load (cores) above which a run counts as disturbed and is retried")
    opts = ap.parse_args()
    {"scaling": scaling, "precision": precision, "taichi": taichi}[opts.what](opts)


if __name__ == "__main__":
    main()
