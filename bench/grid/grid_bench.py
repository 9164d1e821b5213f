"""km.grid benchmarks: per-stage timings of smoke steps, a work-precision study on Taylor-Green,
and Taichi's bundled stable-fluids example as the side-by-side peer (issue 3, "Speed").

    .venv/bin/python bench/grid/grid_bench.py             # the issue's figures, one run (~5 min quiet)
    .venv/bin/python bench/grid/grid_bench.py --quick     # 256^2 / 48^3 smoke, small sweep (~1 min)
    .venv/bin/python bench/grid/grid_bench.py --only 3d --steps 4   # the 128^3 smoke step alone
    .venv/bin/python bench/grid/grid_bench.py --only 3d --steps 3 --kernel nodes auto --rounds 2
        # before/after the row advection kernels, alternating in one run

One run gives: the 2D 512^2 smoke step (MacCormack, MGPCG to 1e-6) and its ratios to Taichi's
stable_fluid.py step with 500 Jacobi iterations and with MGPCG, the 3D 128^3 smoke step, each
with per-stage seconds and the CPU seconds of the process (wall x busy threads: on a loaded
machine the wall time of a 2-thread step swells with every descheduled barrier, the CPU time
much less), the work-precision study, and periodic-Poisson MGPCG iteration counts. A summary
table is written to bench/out/grid_summary.md.

Outputs bench/out/grid.csv (harness.Recorder rows: per-stage seconds in the notes) and
bench/out/grid_taylor_green.png (work-precision: wall time against the L2 velocity error).

Peer: taichi/examples/simulation/stable_fluid.py from the installed taichi wheel, imported in a
subprocess (it calls ti.init and parses sys.argv at import) and driven headless through its own
kernels with a fixed impulse. Its step is timed with the default 500 Jacobi iterations, and the
divergence left after them is measured with its own divergence kernel (before/after the pressure
solve). The "MGPCG" peer figure is composed: the same step with 0 Jacobi iterations plus the
steady-state solve of Taichi's bundled MGPCG (bench/poisson/peers.py, TaichiMGPCG) at the same size and
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
sys.path.insert(0, str(HERE.parent / "common"))  # harness.py
sys.path.insert(0, str(HERE.parent / "poisson"))  # peers.py (Taichi's MGPCG)
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = HERE.parent / "out"


# ------------------------------------------------------------------ kinema

def smoke(shape, *, advection="maccormack", tol=1e-6, kernel="auto"):
    """A buoyant smoke plume: source near the floor, a round obstacle above it."""
    n = shape[0]
    d = len(shape)
    g = [0.0] * d
    g[1] = -9.81
    f = km.grid.Fluid(shape, 1.0 / n, advection=advection, tol=tol, density=True, temperature=True,
                      buoyancy=(0.05, 1.0), gravity=g, vorticity_confinement=0.2, advection_kernel=kernel)
    centre = [(i + 0.5) / n for i in range(n)]
    grids = np.meshgrid(*[np.asarray(centre) * shape[a] / n for a in range(d)], indexing="ij")
    r2 = sum((x - c) ** 2 for x, c in zip(grids, [0.5] + [0.55] + [0.5] * (d - 2)))
    f.solid[...] = r2 < 0.1**2
    src = tuple([slice(2 * n // 5, 3 * n // 5), slice(2, 2 + max(2, n // 32))] + [slice(2 * n // 5, 3 * n // 5)] * (d - 2))
    return f, src


def time_smoke(shape, rec, *, steps=3, advection="maccormack", kernel="auto"):
    f, src = smoke(shape, advection=advection, kernel=kernel)
    dt = 0.5 / shape[0]
    for _ in range(3):  # develop a flow first, so the projection has work to do
        f.density[src] = 1.0
        f.temperature[src] = 1.0
        f.step(dt)

    def one():
        f.density[src] = 1.0
        f.temperature[src] = 1.0
        cpu = time.process_time()
        info = f.step(dt)
        return info, time.process_time() - cpu

    m = harness.measure(one, min_of=steps, max_tries=steps + 2)
    info, cpu = m.value
    div = np.linalg.norm(f.divergence())
    assert info.pressure.converged and info.pressure.residual <= 1e-6, info.pressure
    stages = {k: round(getattr(info, f"{k}_seconds"), 4) for k in ("advect", "forces", "viscosity", "projection")}
    stages["total"] = round(info.seconds, 4)
    name = f"kinema-smoke-{advection}" + ("" if kernel == "auto" else f"-{kernel}")
    rec.record(name, shape, m.seconds, error=info.pressure.residual,
               iterations=info.pressure.iterations, measurement=m,
               notes={**stages, "cpu_s": round(cpu, 4), "div_l2": f"{div:.2e}"})
    print(f"kinema smoke {shape} {advection}{'' if kernel == 'auto' else ' ' + kernel}: {m.seconds:.3f} s/step (cpu {cpu:.3f} s, other load "
          f"{m.other_load:.2f}{', disturbed' if m.disturbed else ''}), pressure {info.pressure.iterations} it, "
          f"residual {info.pressure.residual:.1e}, stages {stages}", flush=True)
    return {"seconds": m.seconds, "cpu": cpu, "load": m.other_load, "disturbed": m.disturbed,
            "stages": stages, "iterations": info.pressure.iterations, "residual": info.pressure.residual}


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
    study = {}
    for advection in km.grid.SCHEMES:
        for n in sizes:
            m = harness.measure(lambda: taylor_green_error(n, advection), min_of=1, max_tries=2)
            seconds, err = m.value
            rec.record(f"kinema-{advection}", (n, n), seconds, error=err, measurement=m)
            study[advection, n] = (seconds, err)
            print(f"taylor-green {advection} {n}^2: {seconds:.3f} s, L2 error {err:.3e} "
                  f"(other load {m.other_load:.2f})", flush=True)
    return study


def periodic_poisson(sizes, rec):
    """Iterations of km.poisson's periodic MGPCG against CG (tol 1e-8, random right-hand side)."""
    rng = np.random.default_rng(0)
    rows = []
    for shape in sizes:
        f = rng.standard_normal(shape)
        f -= f.mean()
        row = {"shape": shape}
        for method in ("mgpcg", "cg"):
            m = harness.measure(lambda: km.poisson.solve(f, 1.0 / shape[0], "periodic", method=method, tol=1e-8),
                                min_of=1, max_tries=2)
            info = m.value[1]
            rec.record(f"kinema-periodic-{method}", shape, m.seconds, error=info.residual,
                       iterations=info.iterations, measurement=m)
            row[method] = (info.iterations, m.seconds)
        rows.append(row)
        print(f"periodic poisson {shape}: mgpcg {row['mgpcg'][0]} it {row['mgpcg'][1]:.3f} s, "
              f"cg {row['cg'][0]} it {row['cg'][1]:.3f} s", flush=True)
    return rows


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
    times, cpus = [], []
    for _ in range(steps):
        start, cpu = time.perf_counter(), time.process_time()
        sf.step(mouse)
        sf.ti.sync()
        times.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
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
    print(json.dumps({"res": res, "seconds": min(times), "times": times, "cpu": cpus[int(np.argmin(times))],
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
    p.add_argument("--only", choices=["3d"], help="only the 3D smoke step (128^3, 48^3 with --quick); "
                   "with --steps, the min over that many timed steps")
    p.add_argument("--steps", type=int, default=2, help="timed steps of the 3D smoke case (default 2)")
    p.add_argument("--kernel", nargs="+", default=["auto"], choices=km.grid.ADVECTION_KERNELS,
                   help="with --only 3d: the advection kernels to time, in turn (e.g. 'nodes auto' for "
                   "before/after: 'nodes' is the node-wise code the row kernels replaced)")
    p.add_argument("--rounds", type=int, default=1, help="with --only 3d: repeat the kernels this many times")
    args = p.parse_args(argv)
    if args.taichi_worker:
        taichi_worker(*args.taichi_worker)
        return 0
    threads = harness.default_threads()
    km.set_num_threads(threads)
    rec = harness.Recorder(OUT / "grid.csv", benchmark="grid_smoke", threads=threads)
    n2, n3 = (256, 48) if args.quick else (512, 128)
    print(f"kinema {km.__version__}, {threads} threads, commit {harness.git_commit(HERE)}", flush=True)
    if args.only == "3d":
        for _ in range(args.rounds):
            for kernel in args.kernel:
                time_smoke((n3, n3, n3), rec, steps=args.steps, kernel=kernel)
        return 0
    k2 = time_smoke((n2, n2), rec)
    k3 = time_smoke((n3, n3, n3), rec, steps=args.steps)
    sl2 = time_smoke((n2, n2), rec, advection="semi_lagrangian")

    jac = mg = bare = None
    if not args.no_taichi and importlib.util.find_spec("taichi") is not None:
        jac = run_taichi(500, 3, threads)
        rec.record("taichi-stable_fluid-jacobi500", (jac["res"],) * 2, jac["seconds"],
                   error=jac["divergence_left"], iterations=500,
                   notes={"other_load": f"{jac['other_load']:.2f}", "cpu_s": round(jac["cpu"], 4),
                          "example": "stable_fluid.py"})
        print(f"taichi stable_fluid {jac['res']}^2 Jacobi(500): {jac['seconds']:.3f} s/step (cpu {jac['cpu']:.3f} s), "
              f"divergence left {100 * jac['divergence_left']:.0f}% (other load {jac['other_load']:.2f})", flush=True)
        bare = run_taichi(0, 3, threads)
        import peers

        b = peers.poisson_rhs((jac["res"], jac["res"]), 1.0 / jac["res"], kind="random")
        before = harness.sample_cpu()
        mg = peers.taichi_mgpcg(b, tol=1e-6, threads=threads)
        mg_load = harness.other_load(before, harness.sample_cpu())
        composed = bare["seconds"] + mg.seconds["solve"]
        rec.record("taichi-stable_fluid+mgpcg(composed)", (jac["res"],) * 2, composed,
                   error=mg.residual, iterations=mg.iterations,
                   notes={"step_without_solve": f"{bare['seconds']:.3f}", "mgpcg_solve": f"{mg.seconds['solve']:.3f}",
                          "other_load": f"{max(bare['other_load'], mg_load):.2f}"})
        mg = {"seconds": composed, "iterations": mg.iterations, "residual": mg.residual,
              "load": max(bare["other_load"], mg_load)}
        print(f"taichi step + MGPCG (composed): {composed:.3f} s/step ({mg['iterations']} it)", flush=True)

    wp = harness.Recorder(OUT / "grid.csv", benchmark="grid_taylor_green", threads=threads)
    study = work_precision((16, 32) if args.quick else (16, 32, 64, 128), wp)
    png = harness.plot_work_precision(OUT / "grid.csv", OUT / "grid_taylor_green.png",
                                      benchmark="grid_taylor_green")
    print(f"work-precision plot: {png}")
    pp = harness.Recorder(OUT / "grid.csv", benchmark="grid_periodic_poisson", threads=threads)
    periodic = periodic_poisson([(64, 64), (128, 128), (256, 256)] + ([] if args.quick else [(512, 512)]) +
                                [(16, 16, 16), (32, 32, 32)] + ([] if args.quick else [(64, 64, 64)]), pp)
    summary = write_summary(OUT / "grid_summary.md", threads, n2, n3, k2, k3, sl2, jac, mg, study, periodic)
    print(summary)
    return 0


def write_summary(path, threads, n2, n3, k2, k3, sl2, jac, mg, study, periodic):
    load = lambda r: f"{r['load']:.2f}" + (" (disturbed)" if r.get("disturbed") else "")  # noqa: E731
    stage = lambda r: " / ".join(f"{r['stages'][k]:.3f}" for k in ("advect", "forces", "projection"))  # noqa: E731
    lines = [f"commit {harness.git_commit(HERE)}, {threads} threads, "
             f"OMP_WAIT_POLICY={__import__('os').environ.get('OMP_WAIT_POLICY', 'unset')}", "",
             "| case | s/step (wall) | CPU s/step | stages [s] advect / forces / projection | pressure it | other_load |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, r in ((f"2D {n2}^2 MacCormack", k2), (f"3D {n3}^3 MacCormack", k3), (f"2D {n2}^2 semi-Lagrangian", sl2)):
        lines.append(f"| {name} | {r['seconds']:.3f} | {r['cpu']:.3f} | {stage(r)} | {r['iterations']} | {load(r)} |")
    if jac:
        lines.append(f"| Taichi stable_fluid.py {jac['res']}^2, 500 Jacobi | {jac['seconds']:.3f} | {jac['cpu']:.3f} | "
                     f"leaves {100 * jac['divergence_left']:.0f}% of the divergence | 500 | {jac['other_load']:.2f} |")
        lines.append(f"| Taichi step without solve + Taichi MGPCG (tol 1e-6, cold) | {mg['seconds']:.3f} | | "
                     f"residual {mg['residual']:.1e} | {mg['iterations']} | {mg['load']:.2f} |")
        if jac["res"] == n2:
            lines += ["", f"Ratios (same run): Taichi-Jacobi / kinema = {jac['seconds'] / k2['seconds']:.2f} "
                      f"(target >= 4); Taichi-MGPCG / kinema = {mg['seconds'] / k2['seconds']:.2f} (target >= 20); "
                      f"3D {n3}^3 step {k3['seconds']:.2f} s (target < 1 s)."]
    lines += ["", "| n | " + " | ".join(km.grid.SCHEMES) + " | s (maccormack) |", "| --- |" + " --- |" * (len(km.grid.SCHEMES) + 1)]
    for n in sorted({n for (_, n) in study}):
        errs = " | ".join(f"{study[s, n][1]:.2e}" for s in km.grid.SCHEMES)
        lines.append(f"| {n} | {errs} | {study['maccormack', n][0]:.3f} |")
    lines += ["", "| periodic Poisson | MGPCG it (s) | CG it (s) |", "| --- | --- | --- |"]
    for row in periodic:
        shape = "x".join(map(str, row["shape"]))
        lines.append(f"| {shape} | {row['mgpcg'][0]} ({row['mgpcg'][1]:.3f}) | {row['cg'][0]} ({row['cg'][1]:.3f}) |")
    text = "\n".join(lines) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


if __name__ == "__main__":
    sys.exit(main())
