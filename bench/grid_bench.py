"""km.grid benchmarks: per-stage timings of smoke steps, a work-precision study on Taylor-Green,
and Taichi's bundled stable-fluids example as the side-by-side peer (issue 3, "Speed").

    .venv/bin/python bench/grid_bench.py --quick     # 256^2 / 48^3 smoke, small sweep (~1 min)
    .venv/bin/python bench/grid_bench.py             # 512^2 / 128^3 smoke, Taichi at 512^2

Outputs bench/out/grid.csv (harness.Recorder rows: per-stage seconds in the notes) and
bench/out/grid_taylor_green.png (work-precision: wall time against the L2 velocity error).

Peer: taichi/examples/simulation/stable_fluid.py from the installed taichi wheel, imported in a
subprocess (it calls ti.init and parses sys.argv at import) and driven headless through its own
kernels with a fixed impulse. Its step is timed with the default 500 Jacobi iterations, and the
divergence left after them is measured with its own divergence kernel (before/after the pressure
solve). The "MGPCG" peer figure is composed: the same step with 0 Jacobi iterations plus the
steady-state solve of Taichi's bundled MGPCG (bench/peers.py, TaichiMGPCG) at the same size and
tol 1e-6, since stable_fluid.py has no MGPCG option of its own.
Every figure records the cores other processes used while it ran (other_load); on a shared
machine treat them as orientation.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = HERE / "out"


# ------------------------------------------------------------------ kinema

def smoke(shape, *, advection="maccormack", tol=1e-6):
    """A buoyant smoke plume: source near the floor, a round obstacle above it."""
    n = shape[0]
    d = len(shape)
    g = [0.0] * d
    g[1] = -9.81
    f = km.grid.Fluid(shape, 1.0 / n, advection=advection, tol=tol, density=True, temperature=True,
                      buoyancy=(0.05, 1.0), gravity=g, vorticity_confinement=0.2)
    centre = [(i + 0.5) / n for i in range(n)]
    grids = np.meshgrid(*[np.asarray(centre) * shape[a] / n for a in range(d)], indexing="ij")
    r2 = sum((x - c) ** 2 for x, c in zip(grids, [0.5] + [0.55] + [0.5] * (d - 2)))
    f.solid[...] = r2 < 0.1**2
    src = tuple([slice(2 * n // 5, 3 * n // 5), slice(2, 2 + max(2, n // 32))] + [slice(2 * n // 5, 3 * n // 5)] * (d - 2))
    return f, src


def time_smoke(shape, rec, *, steps=3, advection="maccormack"):
    f, src = smoke(shape, advection=advection)
    dt = 0.5 / shape[0]
    for _ in range(3):  # develop a flow first, so the projection has work to do
        f.density[src] = 1.0
        f.temperature[src] = 1.0
        f.step(dt)

    def one():
        f.density[src] = 1.0
        f.temperature[src] = 1.0
        return f.step(dt)

    m = harness.measure(one, min_of=steps, max_tries=steps + 2)
    info = m.value
    div = np.linalg.norm(f.divergence())
    assert info.pressure.converged and info.pressure.residual <= 1e-6, info.pressure
    stages = {k: round(v, 4) for k, v in info.seconds.items()}
    rec.record(f"kinema-smoke-{advection}", shape, m.seconds, error=info.pressure.residual,
               iterations=info.pressure.iterations, measurement=m,
               notes={**stages, "div_l2": f"{div:.2e}"})
    print(f"kinema smoke {shape} {advection}: {m.seconds:.3f} s/step (other load {m.other_load:.2f}), "
          f"pressure {info.pressure.iterations} it, residual {info.pressure.residual:.1e}, stages {stages}")
    return m.seconds


def taylor_green_error(n, advection, T=0.2, nu=0.01, cfl=1.0):
    k = 2 * np.pi
    h = 0.5 / n
    f = km.grid.Fluid((n, n), h, advection=advection, viscosity=nu, tol=1e-8)
    xf, xc = np.arange(n + 1) * h, (np.arange(n) + 0.5) * h
    f.u[...] = np.sin(k * xf)[:, None] * np.cos(k * xc)[None, :]
    f.v[...] = -np.cos(k * xc)[:, None] * np.sin(k * xf)[None, :]
    steps = int(round(T / (cfl * h)))
    start = time.perf_counter()
    for _ in range(steps):
        f.step(T / steps)
    seconds = time.perf_counter() - start
    ue = np.exp(-2 * k**2 * nu * T) * np.sin(k * xf)[:, None] * np.cos(k * xc)[None, :]
    return seconds, float(np.linalg.norm(f.u - ue) / np.linalg.norm(ue))


def work_precision(sizes, rec):
    for advection in km.grid.SCHEMES:
        for n in sizes:
            m = harness.measure(lambda: taylor_green_error(n, advection), min_of=1, max_tries=2)
            seconds, err = m.value
            rec.record(f"kinema-{advection}", (n, n), seconds, error=err, measurement=m)
            print(f"taylor-green {advection} {n}^2: {seconds:.3f} s, L2 error {err:.3e}")


# ------------------------------------------------------------------ Taichi peer

def _stable_fluid_module():
    import taichi

    path = Path(taichi.__file__).parent / "examples" / "simulation" / "stable_fluid.py"
    if not path.exists():
        raise ImportError(f"taichi {taichi.__version__} ships no {path}")
    sys.argv = [str(path), "--arch", "cpu"]
    spec = importlib.util.spec_from_file_location("taichi_example_stable_fluid", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def taichi_worker(jacobi_iters, steps):
    """Runs in a subprocess: times the example's step, prints JSON."""
    sf = _stable_fluid_module()
    sf.p_jacobi_iters = jacobi_iters
    res = sf.res
    mouse = np.zeros(8, dtype=np.float32)
    mouse[0:2] = (0.0, 1.0)
    mouse[2:4] = (res / 2, res / 4)
    mouse[4:7] = (1.0, 0.8, 0.5)
    for _ in range(3):  # JIT and a developed flow
        sf.step(mouse)
    sf.ti.sync()
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        sf.step(mouse)
        sf.ti.sync()
        times.append(time.perf_counter() - start)
    # divergence before and after the pressure solve, by the example's own kernels
    v = sf.velocities_pair
    sf.advect(v.cur, v.cur, v.nxt)
    v.swap()
    sf.apply_impulse(v.cur, sf.dyes_pair.cur, mouse)
    sf.divergence(v.cur)
    before = float(np.linalg.norm(sf.velocity_divs.to_numpy()))
    sf.solve_pressure_jacobi()
    sf.subtract_gradient(v.cur, sf.pressures_pair.cur)
    sf.divergence(v.cur)
    after = float(np.linalg.norm(sf.velocity_divs.to_numpy()))
    print(json.dumps({"res": res, "seconds": min(times), "times": times,
                      "divergence_left": after / before if before > 0 else 0.0}))


def run_taichi(jacobi_iters, steps, threads):
    import os

    env = dict(os.environ, OMP_NUM_THREADS=str(threads), TI_NUM_THREADS=str(threads))
    before = harness.sample_cpu()
    out = subprocess.run([sys.executable, __file__, "--taichi-worker", str(jacobi_iters), str(steps)],
                         capture_output=True, text=True, env=env, check=True)
    after = harness.sample_cpu()
    line = [s for s in out.stdout.splitlines() if s.startswith("{")][-1]
    result = json.loads(line)
    result["other_load"] = harness.other_load(before, after)
    return result


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--no-taichi", action="store_true")
    p.add_argument("--taichi-worker", nargs=2, type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.taichi_worker:
        taichi_worker(*args.taichi_worker)
        return 0
    threads = harness.default_threads()
    km.set_num_threads(threads)
    rec = harness.Recorder(OUT / "grid.csv", benchmark="grid_smoke", threads=threads)
    n2, n3 = (256, 48) if args.quick else (512, 128)
    t2 = time_smoke((n2, n2), rec)
    time_smoke((n3, n3, n3), rec, steps=2)
    if not args.quick:
        time_smoke((n2, n2), rec, advection="semi_lagrangian")

    wp = harness.Recorder(OUT / "grid.csv", benchmark="grid_taylor_green", threads=threads)
    work_precision((16, 32) if args.quick else (16, 32, 64, 128), wp)
    png = harness.plot_work_precision(OUT / "grid.csv", OUT / "grid_taylor_green.png",
                                      benchmark="grid_taylor_green")
    print(f"work-precision plot: {png}")

    if not args.no_taichi and importlib.util.find_spec("taichi") is not None:
        jac = run_taichi(500, 3, threads)
        rec.record("taichi-stable_fluid-jacobi500", (jac["res"],) * 2, jac["seconds"],
                   error=jac["divergence_left"], iterations=500,
                   notes={"other_load": f"{jac['other_load']:.2f}", "example": "stable_fluid.py"})
        print(f"taichi stable_fluid {jac['res']}^2 Jacobi(500): {jac['seconds']:.3f} s/step, "
              f"divergence left {100 * jac['divergence_left']:.0f}% (other load {jac['other_load']:.2f})")
        if jac["res"] == n2:
            print(f"  ratio taichi-jacobi / kinema = {jac['seconds'] / t2:.2f} (target >= 4)")
        bare = run_taichi(0, 3, threads)
        import peers

        b = peers.poisson_rhs((jac["res"], jac["res"]), 1.0 / jac["res"], kind="random")
        mg = peers.taichi_mgpcg(b, tol=1e-6, threads=threads)
        composed = bare["seconds"] + mg.seconds["solve"]
        rec.record("taichi-stable_fluid+mgpcg(composed)", (jac["res"],) * 2, composed,
                   error=mg.residual, iterations=mg.iterations,
                   notes={"step_without_solve": f"{bare['seconds']:.3f}", "mgpcg_solve": f"{mg.seconds['solve']:.3f}"})
        print(f"taichi step + MGPCG (composed): {composed:.3f} s/step ({mg.iterations} it)")
        if jac["res"] == n2:
            print(f"  ratio taichi-mgpcg / kinema = {composed / t2:.2f} (target >= 20)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
