"""Deformable bodies side by side: km.massspring and km.fem against Taichi's bundled examples.

Figures (CSV in bench/out/deform.csv, work-precision plot bench/out/deform_wp.png), all taken
in one run so that their ratios compare like with like:
- cloth: implicit mass-spring steps of a 129 x 129-vertex cloth, kinema's default path
  (exact Jacobian; PCG to 1e-8 preconditioned by a lagged CHOLMOD factor, refactorised when
  PCG slows) and its direct path (a CHOLMOD factorisation every step), against Taichi's
  examples/simulation/implicit_mass_spring.py (its Cloth class, CPU backend, LDLT analysed and
  factorised every step as the example does), same layout, stiffness 1000, damping 0.5, unit
  masses, gravity (0, -2), h = 0.01. Taichi's example pins its two corners with penalty springs
  (kf = 1e5) and ships sparse-matrix builders sized for N = 5; the builders are made larger
  here (its code is otherwise untouched).
- cube: implicit steps of the 20^3-vertex cube (19^3 cells x 5 tets = 34,295 tets), E = 5e4,
  nu = 0, rho = 1000, h = 0.01, gravity -9.8 y: kinema's neo-Hookean Newton converged to a
  relative gradient norm of 1e-6 (default and direct paths) against Taichi's
  examples/simulation/implicit_fem.py in its default matrix-free CG mode (one linearisation per
  step, <= 50 CG iterations), whose source is executed from the installed wheel with
  n_cube = 20 and the CPU backend substituted.
- every time per step is the mean over --run-steps consecutive steps (so the default path's
  occasional refactorisations are paid for), with the per-stage split: assembly (gradient +
  Hessian), CHOLMOD factorisation, solve (PCG or triangular solves), line search, per Newton
  iteration; and, on the direct path, assembly per iteration against one factorisation.
- before timing, each case checks that the default and the direct path agree after the same
  steps (to the PCG / Newton tolerance): a fast wrong answer fails the benchmark.
- scaling of the step with the cube size; work precision: dt and Newton tol against the error
  to a fine reference (small beam).

The harness records other processes' load with every figure and repeats disturbed calls
(--max-load, --max-tries, --quiet-timeout). One command for the whole set:
    .venv/bin/python bench/deform/deform_bench.py            (--quick: small sizes, smoke run)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

import kinema as km  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"


def peer(part, size, opts, kinema):
    """Runs the Taichi peer (bench/deform/deform_taichi_peer.py) in its own process, so that a crash
    of the peer cannot end the whole run. kinema: the kinema default's Measurement, for the
    printed ratios."""
    import subprocess
    sys.stdout.flush()
    args = [sys.executable, str(Path(__file__).with_name("deform_taichi_peer.py")), part, str(size),
            "--threads", str(opts.threads), "--run-steps", str(opts.run_steps), "--min-of", str(opts.min_of),
            "--max-load", str(opts.max_load), "--max-tries", str(opts.max_tries),
            "--quiet-timeout", str(opts.quiet_timeout),
            "--kinema", f"{kinema.seconds}", f"{kinema.value[1]}"]
    done = subprocess.run(args)
    if done.returncode != 0:
        print(f"taichi {part} peer: process ended with status {done.returncode}; no figure", flush=True)


def measure(fn, opts, min_of=None):
    """harness.measure with the command line's repeat policy: disturbed calls are repeated."""
    return harness.measure(fn, min_of=min_of or opts.min_of, max_load=opts.max_load,
                           max_tries=opts.max_tries, quiet_timeout=opts.quiet_timeout)


# ---------------------------------------------------------------- cloth

def kinema_cloth(N):
    """Taichi's cloth layout: (N+1)^2 vertices in [0.25, 0.75]^2, structural + both diagonals."""
    x, springs, kinds = km.massspring.cloth(N + 1, N + 1, 0.5, dim=2, return_kinds=True)
    x += 0.25
    springs = springs[kinds < 2]
    NV = (N + 1) ** 2
    return km.massspring.System(x, springs, stiffness=1000.0, damping=0.5, mass=1.0,
                                gravity=(0.0, -2.0), fixed=[N, NV - 1])


def bench_cloth(rec, N, opts):
    # The benchmark checks its answer first: the default (lagged factor, PCG to 1e-8) and the
    # direct solve every step give the same cloth after the same steps.
    a, b = kinema_cloth(N), kinema_cloth(N)
    for _ in range(opts.run_steps):
        a.step(0.01)
        b.step(0.01, linear_solver="cholmod_direct")
    diff = np.abs(a.x - b.x).max()
    print(f"cloth: default vs direct after {opts.run_steps} steps: max |dx| {diff:.1e} m")
    assert diff < 1e-8, f"cloth: default and direct paths differ by {diff:.2e}"
    m = bench_cloth_kinema(rec, N, opts, "cholmod")
    bench_cloth_kinema(rec, N, opts, "cholmod_direct")
    peer("cloth", N, opts, m)


def bench_cloth_kinema(rec, N, opts, solver):
    """Mean time per step over opts.run_steps consecutive steps (refactorisations included)."""
    sysk = kinema_cloth(N)
    sysk.step(0.01, linear_solver=solver)  # analysis + first factorisation, not timed
    k = opts.run_steps

    def k_steps():
        infos = [sysk.step(0.01, linear_solver=solver) for _ in range(k)]
        return {f: sum(getattr(i, f) for i in infos) for f in
                ("seconds_assembly", "seconds_factor", "seconds_solve", "cg_iterations", "factorizations")}

    m = measure(harness.with_cpu(k_steps), opts)
    t, cpu = m.value
    assert np.isfinite(sysk.x).all()
    rec.record(f"kinema_implicit_cloth_{solver}", f"{N+1}x{N+1}", m.seconds / k, measurement=m,
               iterations=t["cg_iterations"],
               notes={"steps": k, "cpu_per_step": f"{cpu/k:.4f}", "factorizations": t["factorizations"],
                      "assembly": f"{t['seconds_assembly']/k:.4f}", "factor": f"{t['seconds_factor']/k:.4f}",
                      "solve": f"{t['seconds_solve']/k:.4f}"})
    print(f"cloth {N+1}^2 kinema {solver}: {m.seconds/k*1e3:.1f} ms/step, CPU {cpu/k*1e3:.1f} ms/step "
          f"(mean of {k}; per step assembly "
          f"{t['seconds_assembly']/k*1e3:.1f}, factor {t['seconds_factor']/k*1e3:.1f}, solve "
          f"{t['seconds_solve']/k*1e3:.1f} ms; {t['factorizations']} factorisations, {t['cg_iterations']} PCG its; "
          f"load {m.other_load:.2f}, {m.repeats} tries)")
    return m


# ---------------------------------------------------------------- cube

def cube_body(n):
    V, T = km.fem.box_mesh([0, 1, 0], [1, 2, 1], n - 1, tets_per_cell=5)
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=5e4, poisson_ratio=0.0,
                       density=1000.0, gravity=(0, -9.8, 0))
    body.v[:, 0] = 1.0
    body.v[V[:, 1] > 1.5, 2] = 0.5  # a shear so that Newton has work beyond free fall
    return body, T


def bench_cube(rec, n, opts):
    # The benchmark checks its answer first: the default (lagged factor as PCG preconditioner)
    # and the direct path (a factorisation per Newton iteration), both stopped at a relative
    # gradient norm of 1e-6, give the same body after the same steps.
    a, b = cube_body(n)[0], cube_body(n)[0]
    for _ in range(opts.run_steps):
        a.step(0.01, tol=1e-6)
        b.step(0.01, tol=1e-6, linear_solver="cholmod_direct")
    diff, scale = np.abs(a.x - b.x).max(), np.abs(b.x - b.rest).max()
    print(f"cube: default vs direct after {opts.run_steps} steps: max |dx| {diff:.1e} m "
          f"(displacement {scale:.2f} m)")
    assert diff < 1e-5 * scale, f"cube: default and direct differ by {diff:.2e}"
    ma = bench_cube_kinema(rec, n, opts, "cholmod")
    mb = bench_cube_kinema(rec, n, opts, "cholmod_direct")
    t = mb.value[0]
    print(f"assembly vs factorisation (direct path): {t['seconds_assembly']/t['iterations']*1e3:.1f} ms "
          f"per Newton iteration (gradient + Hessian) vs {t['seconds_factor']/t['factorizations']*1e3:.1f} ms "
          f"per CHOLMOD factorisation")
    peer("cube", n, opts, ma)


def bench_cube_kinema(rec, n, opts, solver):
    """Mean time per step over opts.run_steps consecutive steps (refactorisations included)."""
    body, T = cube_body(n)
    body.step(0.01, linear_solver=solver)  # analysis + first factorisation, not timed
    k = opts.run_steps
    fields = ("iterations", "cg_iterations", "factorizations", "seconds_assembly", "seconds_factor",
              "seconds_solve", "seconds_line_search")

    def k_steps():
        infos = [body.step(0.01, tol=1e-6, linear_solver=solver) for _ in range(k)]
        assert all(i.converged and i.residual <= 1e-6 for i in infos)
        t = {f: sum(getattr(i, f) for i in infos) for f in fields}
        t["residual"] = max(i.residual for i in infos)
        return t

    m = measure(harness.with_cpu(k_steps), opts)
    t, cpu = m.value
    it = max(t["iterations"], 1)
    rec.record(f"kinema_neohookean_newton_{solver}", f"{n}^3 verts, {len(T)} tets", m.seconds / k,
               iterations=t["iterations"], error=t["residual"], measurement=m,
               notes={"steps": k, "cpu_per_step": f"{cpu/k:.4f}", "factorizations": t["factorizations"],
                      "pcg_its": t["cg_iterations"],
                      "assembly_per_it": f"{t['seconds_assembly']/it:.4f}",
                      "factor_per_it": f"{t['seconds_factor']/it:.4f}",
                      "solve_per_it": f"{t['seconds_solve']/it:.4f}",
                      "line_search_per_it": f"{t['seconds_line_search']/it:.4f}"})
    print(f"cube {n}^3 ({len(T)} tets) kinema {solver}: {m.seconds/k:.3f} s/step, CPU {cpu/k:.3f} s/step "
          f"(mean of {k}), "
          f"{t['iterations']/k:.1f} Newton its/step, {t['factorizations']} factorisations, "
          f"{t['cg_iterations']} PCG its; per Newton it: assembly {t['seconds_assembly']/it*1e3:.1f} ms, "
          f"factor {t['seconds_factor']/it*1e3:.1f} ms, solve {t['seconds_solve']/it*1e3:.1f} ms, "
          f"line search {t['seconds_line_search']/it*1e3:.1f} ms (load {m.other_load:.2f}, {m.repeats} tries)")
    return m


def bench_scaling(rec, sizes, opts):
    for n in sizes:
        V, T = km.fem.box_mesh([0, 0, 0], [1, 1, 1], n - 1, tets_per_cell=5)
        body = km.fem.Body(V, T, youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0,
                           fixed=np.flatnonzero(V[:, 0] < 1e-12), gravity=(0, -9.8, 0))
        body.step(0.01)
        m = measure(lambda: body.step(0.01), opts)
        info = m.value
        it = max(info.iterations, 1)
        rec.record("kinema_neohookean_newton_scaling", f"{n}^3", m.seconds, iterations=info.iterations,
                   measurement=m, notes={"assembly_per_it": f"{info.seconds_assembly/it:.4f}",
                                         "factor_per_it": f"{info.seconds_factor/it:.4f}",
                                         "solve_per_it": f"{info.seconds_solve/it:.4f}"})
        print(f"scaling {n}^3: {m.seconds:.3f} s/step, {info.iterations} its, assembly/it "
              f"{info.seconds_assembly/it*1e3:.1f} ms, factor/it {info.seconds_factor/it*1e3:.1f} ms, "
              f"{info.factorizations} factorisations, {info.cg_iterations} PCG its (load {m.other_load:.2f})")


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


def bench_work_precision(rec, opts):
    ref = run_beam(0.2 / 256, 1e-10)
    scale = np.abs(ref - beam().rest).max()
    for dt in (0.2 / 4, 0.2 / 8, 0.2 / 16, 0.2 / 32, 0.2 / 64):
        m = measure(lambda: run_beam(dt, 1e-8), opts, min_of=1)
        err = np.abs(m.value - ref).max() / scale
        rec.record("kinema_fem_wp_dt", "beam 10x2x2", m.seconds, error=err, measurement=m,
                   notes={"dt": dt})
        print(f"wp dt={dt:.4f}: {m.seconds:.3f} s, rel. error {err:.2e}")
    fine = run_beam(0.2 / 16, 1e-12)
    for tol in (1e-2, 1e-4, 1e-6, 1e-8):
        m = measure(lambda: run_beam(0.2 / 16, tol), opts, min_of=1)
        err = np.abs(m.value - fine).max() / scale
        rec.record("kinema_fem_wp_tol", "beam 10x2x2", m.seconds, error=err, measurement=m,
                   notes={"tol": tol})
        print(f"wp tol={tol:.0e}: {m.seconds:.3f} s, rel. error to tol=1e-12 {err:.2e}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    parser.add_argument("--run-steps", type=int, default=10,
                        help="consecutive steps per timed call (time per step = their mean)")
    parser.add_argument("--min-of", type=int, default=2, help="undisturbed timed calls per figure")
    parser.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD,
                        help="a call is disturbed when other processes used more cores than this")
    parser.add_argument("--max-tries", type=int, default=harness.DEFAULT_MAX_TRIES,
                        help="timed calls at most per figure, disturbed ones included")
    parser.add_argument("--quiet-timeout", type=float, default=harness.DEFAULT_QUIET_TIMEOUT,
                        help="wait at most this long [s] for a quiet machine before a retry")
    parser.add_argument("--only", choices=["cloth", "cube", "scaling", "wp"], help="one part only")
    parser.add_argument("--threads", type=int, default=None,
                        help="threads for kinema and Taichi alike (default: kinema's default)")
    opts = parser.parse_args()
    opts.threads = opts.threads or harness.default_threads()
    km.set_num_threads(opts.threads)
    rec = harness.Recorder(OUT / "deform.csv", "deform", threads=opts.threads)
    N, n = (32, 8) if opts.quick else (128, 20)
    print(f"threads {opts.threads}, commit {rec.commit}")
    run = lambda part: opts.only in (None, part)  # noqa: E731
    if run("cloth"):
        bench_cloth(rec, N, opts)
    if run("cube"):
        bench_cube(rec, n, opts)
    if run("scaling"):
        bench_scaling(rec, (6, 10) if opts.quick else (8, 12, 16, 20), opts)
    if run("wp"):
        bench_work_precision(rec, opts)
    try:
        harness.plot_work_precision(OUT / "deform.csv", OUT / "deform_wp.png", benchmark="deform")
    except Exception as exc:
        print(f"plot skipped: {exc}")


if __name__ == "__main__":
    main()
