"""Deformable bodies side by side: km.massspring and km.fem against Taichi's bundled examples.

Figures (CSV in bench/out/deform.csv, work-precision plot bench/out/deform_wp.png):
- cloth: one implicit mass-spring step of a 129 x 129-vertex cloth, kinema (exact Jacobian,
  CHOLMOD with the analysis reused) against Taichi's examples/simulation/implicit_mass_spring.py
  (its Cloth class, CPU backend, LDLT analysed and factorised every step as the example does),
  same layout, stiffness 1000, damping 0.5, unit masses, gravity (0, -2), h = 0.01. Taichi's
  example pins its two corners with penalty springs (kf = 1e5) and ships sparse-matrix builders
  sized for N = 5; the builders are re-made larger here (its code is otherwise untouched).
- cube: one implicit step of the 20^3-vertex cube (19^3 cells x 5 tets = 34,295 tets), E = 5e4,
  nu = 0, rho = 1000, h = 0.01, gravity -9.8 y: kinema's neo-Hookean Newton converged to a
  relative gradient norm of 1e-6 against Taichi's examples/simulation/implicit_fem.py in its
  default matrix-free CG mode (one linearisation per step, <= 50 CG iterations), whose source
  is executed from the installed wheel with n_cube = 20 and the CPU backend substituted.
- per Newton iteration: assembly (gradient + Hessian), CHOLMOD factorisation, solve.
- work precision: dt and Newton tol against the error to a fine reference (small beam).

The harness records other processes' load with every figure; on a shared machine the figures
are orientation only. Run: .venv/bin/python bench/deform_bench.py [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = Path(__file__).resolve().parent / "out"


# ---------------------------------------------------------------- cloth

def kinema_cloth(N):
    """Taichi's cloth layout: (N+1)^2 vertices in [0.25, 0.75]^2, structural + both diagonals."""
    x, springs, kinds = km.massspring.cloth(N + 1, N + 1, 0.5, dim=2, return_kinds=True)
    x += 0.25
    springs = springs[kinds < 2]
    NV = (N + 1) ** 2
    return km.massspring.System(x, springs, stiffness=1000.0, damping=0.5, mass=1.0,
                                gravity=(0.0, -2.0), fixed=[N, NV - 1])


def taichi_cloth(N):
    import taichi as ti
    from taichi.examples.simulation import implicit_mass_spring as example  # noqa: F401

    cloth = example.Cloth(N=N)
    # The example's builders hold 10,000 triplets (N = 5); make room for N = 128.
    triplets = 16 * cloth.NE + 2 * cloth.NV + 64
    cloth.DBuilder = ti.linalg.SparseMatrixBuilder(2 * cloth.NV, 2 * cloth.NV, max_num_triplets=triplets)
    cloth.KBuilder = ti.linalg.SparseMatrixBuilder(2 * cloth.NV, 2 * cloth.NV, max_num_triplets=triplets)
    return cloth


def bench_cloth(rec, N, steps, threads):
    for solver in ("cholmod", "cholmod_pcg"):
        m = bench_cloth_kinema(rec, N, steps, solver)
    bench_cloth_taichi(rec, N, steps, threads, m)


def bench_cloth_kinema(rec, N, steps, solver):
    sysk = kinema_cloth(N)
    sysk.step(0.01)  # analysis + first factorisation

    def k_step():
        return sysk.step(0.01, linear_solver=solver, cg_tol=1e-8)

    m = harness.measure(k_step, min_of=steps)
    info = m.value
    assert np.isfinite(sysk.x).all()
    rec.record(f"kinema_implicit_cloth_{solver}", f"{N+1}x{N+1}", m.seconds, measurement=m,
               iterations=info.cg_iterations,
               notes={"assembly": f"{info.seconds_assembly:.4f}", "factor": f"{info.seconds_factor:.4f}",
                      "solve": f"{info.seconds_solve:.4f}"})
    print(f"cloth {N+1}^2 kinema {solver}: {m.seconds*1e3:.1f} ms/step (assembly {info.seconds_assembly*1e3:.1f}, "
          f"factor {info.seconds_factor*1e3:.1f}, solve {info.seconds_solve*1e3:.1f}, PCG its {info.cg_iterations}; "
          f"load {m.other_load:.2f})")
    return m


def bench_cloth_taichi(rec, N, steps, threads, m):
    try:
        import taichi as ti
        with contextlib.redirect_stdout(io.StringIO()):
            ti.init(arch=ti.cpu, cpu_max_num_threads=threads)
        cloth = taichi_cloth(N)
        cloth.update(0.01)  # JIT compilation
        mt = harness.measure(lambda: cloth.update(0.01), min_of=steps)
        assert np.isfinite(cloth.pos.to_numpy()).all()
        rec.record("taichi_implicit_mass_spring", f"{N+1}x{N+1}", mt.seconds, measurement=mt)
        print(f"cloth {N+1}^2 taichi: {mt.seconds*1e3:.1f} ms/step (load {mt.other_load:.2f}); "
              f"ratio {mt.seconds / m.seconds:.1f}x")
    except Exception as exc:  # the peer is optional: report, do not hide
        print(f"taichi cloth peer failed: {type(exc).__name__}: {exc}")


# ---------------------------------------------------------------- cube

def taichi_fem_module(n, threads):
    """Executes taichi/examples/simulation/implicit_fem.py from the wheel with n_cube = n, CPU."""
    import taichi
    path = Path(taichi.__file__).parent / "examples" / "simulation" / "implicit_fem.py"
    src = path.read_text()
    for old, new in [("ti.init(arch=ti.cuda)", f"ti.init(arch=ti.cpu, cpu_max_num_threads={threads})"),
                     ("n_cube = np.array([5] * 3)", f"n_cube = np.array([{n}] * 3)")]:
        if old not in src:
            raise RuntimeError(f"{path} changed: cannot find {old!r}")
        src = src.replace(old, new)
    # Taichi reads kernel sources back with inspect, so the edited copy must be a real file
    # (generated here from the installed wheel, never committed).
    copy = OUT / f"taichi_implicit_fem_n{n}.py"
    OUT.mkdir(parents=True, exist_ok=True)
    copy.write_text(src)
    argv, sys.argv = sys.argv, [str(path), "--exp", "implicit", "--gui", "cpu"]
    try:
        spec = importlib.util.spec_from_file_location(f"taichi_implicit_fem_n{n}", copy)
        module = importlib.util.module_from_spec(spec)
        with contextlib.redirect_stdout(io.StringIO()):
            spec.loader.exec_module(module)
    finally:
        sys.argv = argv
    return vars(module)


def bench_cube(rec, n, steps, threads, solvers=("cholmod", "cholmod_pcg")):
    for solver in solvers:
        m, T = bench_cube_kinema(rec, n, steps, solver)
    bench_cube_taichi(rec, n, steps, threads, m)


def bench_cube_kinema(rec, n, steps, solver):
    V, T = km.fem.box_mesh([0, 1, 0], [1, 2, 1], n - 1, tets_per_cell=5)
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=5e4, poisson_ratio=0.0,
                       density=1000.0, gravity=(0, -9.8, 0))
    body.v[:, 0] = 1.0
    body.v[V[:, 1] > 1.5, 2] = 0.5  # a shear so that Newton has work beyond free fall
    body.step(0.01, linear_solver=solver)  # analysis
    box = {}

    def k_step():
        box["info"] = body.step(0.01, tol=1e-6, linear_solver=solver, cg_tol=1e-3)
        return box["info"]

    m = harness.measure(k_step, min_of=steps)
    info = m.value
    assert info.converged and info.residual <= 1e-6
    it = max(info.iterations, 1)
    rec.record(f"kinema_neohookean_newton_{solver}", f"{n}^3 verts, {len(T)} tets", m.seconds,
               iterations=info.iterations, error=info.residual, measurement=m,
               notes={"assembly_per_it": f"{info.seconds_assembly/it:.4f}",
                      "factor_per_it": f"{info.seconds_factor/it:.4f}",
                      "solve_per_it": f"{info.seconds_solve/it:.4f}",
                      "line_search": f"{info.seconds_line_search:.4f}"})
    print(f"cube {n}^3 ({len(T)} tets) kinema {solver}: {m.seconds:.3f} s/step, {info.iterations} Newton its, "
          f"{info.cg_iterations} PCG its, "
          f"per it: assembly {info.seconds_assembly/it*1e3:.1f} ms, factor {info.seconds_factor/it*1e3:.1f} ms, "
          f"solve {info.seconds_solve/it*1e3:.1f} ms, line search {info.seconds_line_search*1e3:.1f} ms total "
          f"(load {m.other_load:.2f})")
    return m, T


def bench_cube_taichi(rec, n, steps, threads, m):
    try:
        ns = taichi_fem_module(n, threads)
        ns["get_vertices"]()
        ns["init"]()
        ns["substep"]()  # JIT
        mt = harness.measure(ns["substep"], min_of=steps)
        x = ns["F_x"].to_numpy()
        assert np.isfinite(x).all()
        rec.record("taichi_implicit_fem_cg", f"{n}^3 verts, {int(ns['n_cells'])} tets", mt.seconds,
                   measurement=mt, notes="one linearisation, <= 50 CG iterations, float32")
        print(f"cube {n}^3 taichi (CG, 1 linearisation): {mt.seconds:.3f} s/step (load {mt.other_load:.2f}); "
              f"ratio {mt.seconds / m.seconds:.2f}x")
    except Exception as exc:
        print(f"taichi fem peer failed: {type(exc).__name__}: {exc}")


def bench_scaling(rec, sizes):
    for n in sizes:
        V, T = km.fem.box_mesh([0, 0, 0], [1, 1, 1], n - 1, tets_per_cell=5)
        body = km.fem.Body(V, T, youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0,
                           fixed=np.flatnonzero(V[:, 0] < 1e-12), gravity=(0, -9.8, 0))
        body.step(0.01)
        m = harness.measure(lambda: body.step(0.01), min_of=2)
        info = m.value
        it = max(info.iterations, 1)
        rec.record("kinema_neohookean_newton_scaling", f"{n}^3", m.seconds, iterations=info.iterations,
                   measurement=m, notes={"assembly_per_it": f"{info.seconds_assembly/it:.4f}",
                                         "factor_per_it": f"{info.seconds_factor/it:.4f}",
                                         "solve_per_it": f"{info.seconds_solve/it:.4f}"})
        print(f"scaling {n}^3: {m.seconds:.3f} s/step, {info.iterations} its, assembly/it "
              f"{info.seconds_assembly/it*1e3:.1f} ms, factor/it {info.seconds_factor/it*1e3:.1f} ms")


# ---------------------------------------------------------------- work precision

def beam():
    V, T = km.fem.box_mesh([0, 0, 0], [1, 0.2, 0.2], (10, 2, 2))
    return km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0,
                       fixed=np.flatnonzero(V[:, 0] < 1e-12), gravity=(0, 0, -9.81))


def run_beam(dt, tol, T_end=0.2):
    b = beam()
    steps = int(round(T_end / dt))
    b.step(dt, tol=tol, steps=steps)
    return b.x.copy()


def bench_work_precision(rec):
    ref = run_beam(0.2 / 256, 1e-10)
    scale = np.abs(ref - beam().rest).max()
    for dt in (0.2 / 4, 0.2 / 8, 0.2 / 16, 0.2 / 32, 0.2 / 64):
        m = harness.measure(lambda: run_beam(dt, 1e-8))
        err = np.abs(m.value - ref).max() / scale
        rec.record("kinema_fem_wp_dt", "beam 10x2x2", m.seconds, error=err, measurement=m,
                   notes={"dt": dt})
        print(f"wp dt={dt:.4f}: {m.seconds:.3f} s, rel. error {err:.2e}")
    fine = run_beam(0.2 / 16, 1e-12)
    for tol in (1e-2, 1e-4, 1e-6, 1e-8):
        m = harness.measure(lambda: run_beam(0.2 / 16, tol))
        err = np.abs(m.value - fine).max() / scale
        rec.record("kinema_fem_wp_tol", "beam 10x2x2", m.seconds, error=err, measurement=m,
                   notes={"tol": tol})
        print(f"wp tol={tol:.0e}: {m.seconds:.3f} s, rel. error to tol=1e-12 {err:.2e}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    parser.add_argument("--steps", type=int, default=3, help="undisturbed timed steps per figure")
    parser.add_argument("--only", choices=["cloth", "cube", "scaling", "wp"], help="one part only")
    args = parser.parse_args()
    threads = harness.default_threads()
    km.set_num_threads(threads)
    rec = harness.Recorder(OUT / "deform.csv", "deform", threads=threads)
    N, n = (32, 8) if args.quick else (128, 20)
    print(f"threads {threads}, commit {rec.commit}")
    run = lambda part: args.only in (None, part)  # noqa: E731
    if run("cloth"):
        bench_cloth(rec, N, args.steps, threads)
    if run("cube"):
        bench_cube(rec, n, args.steps, threads)
    if run("scaling"):
        bench_scaling(rec, (6, 10) if args.quick else (8, 12, 16, 20))
    if run("wp"):
        bench_work_precision(rec)
    try:
        harness.plot_work_precision(OUT / "deform.csv", OUT / "deform_wp.png", benchmark="deform")
    except Exception as exc:
        print(f"plot skipped: {exc}")


if __name__ == "__main__":
    main()
