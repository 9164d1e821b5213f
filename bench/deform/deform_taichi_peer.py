"""Taichi's bundled implicit examples as the peers of bench/deform/deform_bench.py (which runs this script
in its own process, so that a crash of the peer cannot end the whole run).

    .venv/bin/python bench/deform/deform_taichi_peer.py {cloth,cube} SIZE [--threads T] [--kinema WALL CPU]

cloth: examples/simulation/implicit_mass_spring.py's Cloth class with N = SIZE (LDLT analysed and
factorised every step, as the example does); its sparse-matrix builders are sized for N = 5 and
are made larger here (taichi_cloth), its code is otherwise untouched. cube: examples/simulation/implicit_fem.py
executed from the installed wheel with n_cube = SIZE and the CPU backend (matrix-free CG, one
linearisation per step, <= 50 CG iterations, float32). Each figure is the mean time per step over
--run-steps consecutive steps, recorded in bench/out/deform.csv with the harness's load.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import sys
from pathlib import Path

import taichi as ti

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"


def measure(fn, opts):
    return harness.measure(fn, min_of=opts.min_of, max_load=opts.max_load, max_tries=opts.max_tries,
                           quiet_timeout=opts.quiet_timeout)


def taichi_cloth(N):
    import taichi.linalg
    from taichi.examples.simulation import implicit_mass_spring as example

    # The example sizes all three of its sparse-matrix builders (mass, damping, stiffness) for
    # N = 5 (10,000 triplets) and fills the mass matrix in its constructor: at N = 128 that
    # overflows the builder (2 NV = 33,282 mass triplets), which crashes or corrupts the run.
    # The builders are made large enough while the Cloth is built; its code is untouched.
    needed = 16 * (2 * N * (N + 1) + 2 * N * N) + 2 * (N + 1) ** 2 + 64
    original = taichi.linalg.SparseMatrixBuilder

    def sized(n, m, max_num_triplets=0, **kwargs):
        return original(n, m, max_num_triplets=max(max_num_triplets, needed), **kwargs)

    taichi.linalg.SparseMatrixBuilder = sized
    try:
        return example.Cloth(N=N)
    finally:
        taichi.linalg.SparseMatrixBuilder = original


def cloth(rec, N, opts):
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            ti.init(arch=ti.cpu, cpu_max_num_threads=opts.threads)
        cloth = taichi_cloth(N)
        cloth.update(0.01)  # JIT compilation
        k = opts.run_steps

        def t_steps():
            for _ in range(k):
                cloth.update(0.01)

        mt = measure(harness.with_cpu(t_steps), opts)
        cpu = mt.value[1]
        assert np.isfinite(cloth.pos.to_numpy()).all()
        rec.record("taichi_implicit_mass_spring", f"{N+1}x{N+1}", mt.seconds / k, measurement=mt,
                   notes={"steps": k, "cpu_per_step": f"{cpu/k:.4f}"})
        print(f"cloth {N+1}^2 taichi: {mt.seconds/k*1e3:.1f} ms/step, CPU {cpu/k*1e3:.1f} ms/step (mean of {k}; "
              f"load {mt.other_load:.2f}, {mt.repeats} tries); ratio taichi / kinema default: wall "
              f"{mt.seconds / opts.kinema[0]:.1f}x, CPU {cpu / opts.kinema[1]:.1f}x (target >= 4x)")
    except Exception as exc:  # the peer is optional: report, do not hide
        print(f"taichi cloth peer failed: {type(exc).__name__}: {exc}")


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


def cube(rec, n, opts):
    try:
        ns = taichi_fem_module(n, opts.threads)
        ns["get_vertices"]()
        ns["init"]()
        ns["substep"]()  # JIT
        k = opts.run_steps

        def t_steps():
            for _ in range(k):
                ns["substep"]()

        mt = measure(harness.with_cpu(t_steps), opts)
        cpu = mt.value[1]
        x = ns["F_x"].to_numpy()
        assert np.isfinite(x).all()
        rec.record("taichi_implicit_fem_cg", f"{n}^3 verts, {int(ns['n_cells'])} tets", mt.seconds / k,
                   measurement=mt, notes={"steps": k, "cpu_per_step": f"{cpu/k:.4f}",
                                          "solver": "one linearisation, <= 50 CG its, float32"})
        print(f"cube {n}^3 taichi (CG, 1 linearisation): {mt.seconds/k:.3f} s/step, CPU {cpu/k:.3f} s/step "
              f"(mean of {k}; load {mt.other_load:.2f}, {mt.repeats} tries); ratio taichi / kinema default: "
              f"wall {mt.seconds / opts.kinema[0]:.2f}x, CPU {cpu / opts.kinema[1]:.2f}x (target >= 2x)")
    except Exception as exc:
        print(f"taichi fem peer failed: {type(exc).__name__}: {exc}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("part", choices=["cloth", "cube"])
    parser.add_argument("size", type=int)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--run-steps", type=int, default=10)
    parser.add_argument("--min-of", type=int, default=2)
    parser.add_argument("--max-load", type=float, default=harness.DEFAULT_MAX_LOAD)
    parser.add_argument("--max-tries", type=int, default=harness.DEFAULT_MAX_TRIES)
    parser.add_argument("--quiet-timeout", type=float, default=harness.DEFAULT_QUIET_TIMEOUT)
    parser.add_argument("--kinema", type=float, nargs=2, default=(float("nan"), float("nan")),
                        metavar=("WALL", "CPU"), help="kinema's seconds for the same steps, for the ratios")
    opts = parser.parse_args()
    rec = harness.Recorder(OUT / "deform.csv", "deform", threads=opts.threads)
    (cloth if opts.part == "cloth" else cube)(rec, opts.size, opts)


if __name__ == "__main__":
    main()
