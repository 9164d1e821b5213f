"""kinema's linear solvers beside their peers, on the problems and targets of issue 2, section 5.

    .venv/bin/python bench/poisson/side_by_side.py --quick          # small grids: checks the wiring (~1 min)
    .venv/bin/python bench/poisson/side_by_side.py                  # the targets at full size
    .venv/bin/python bench/poisson/side_by_side.py --sweep          # plus work-precision sweeps over tol
    .venv/bin/python bench/poisson/side_by_side.py --stream         # plus the STREAM triad (build/bench)
    .venv/bin/python bench/poisson/side_by_side.py --only cholesky --min-of 5 --alternate
                                   # one target, its two codes timed in alternating rounds

Problem: -lap u = f on the cell-centred grid, Dirichlet (ghost = -u), h = 1/N, f random in
[-1, 1) (seed 0, every mode excited). kinema and the matrix peers (PyAMG, SciPy, CHOLMOD via
scikit-sparse) solve exactly this operator (peers.laplacian_matrix). Taichi's MGPCG has its
own vertex-centred operator (peers.TaichiMGPCG): it gets b = h^2 f on the same N^d grid,
float64, from x0 = 0 to the same relative residual ||b - A x|| / ||b||, so the work asked of
both solvers is the same. Every answer is verified by its residual before its time counts.

Each figure goes through harness.measure (repeated when other processes loaded the machine;
min-of-k with --min-of) and into bench/out/side_by_side.csv (work-precision sweeps into
bench/out/work_precision.csv and one plot per grid). kinema's solvers are skipped, with a
note, while km.poisson.solve / km.sparse.cholesky are not built yet.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402
import peers  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"
BENCH_BINARY = Path(__file__).resolve().parents[2] / "build" / "bench" / "kinema_bench"

#: Tolerances of the work-precision sweeps (relative residual).
SWEEP_TOLS = (1e-2, 1e-4, 1e-6, 1e-8, 1e-10)
#: kinema's Poisson methods in the sweeps (jacobi and gauss_seidel need O(N^2) sweeps: left out).
SWEEP_KINEMA_METHODS = ("mgpcg", "multigrid", "cg")
#: Relative residual of the reference solutions the sweeps measure errors against.
REFERENCE_TOL = 1e-12


@dataclass(frozen=True)
class Target:
    """kinema's `ours` must beat `peer` by `ratio` (peer seconds / our seconds) on `shape` to `tol`."""

    name: str
    ours: str
    peer: str
    shape: tuple
    tol: Optional[float]
    ratio: float


def targets(quick: bool) -> list:
    """The ratios of issue 2, section 5 (at small sizes with quick=True, where ratios mean little)."""
    n3, n2 = (32, 128) if quick else (128, 1024)
    return [
        Target("MGPCG 3D vs Taichi MGPCG (1e-6)", "kinema-mgpcg", "taichi", (n3,) * 3, 1e-6, 4.0),
        Target("MGPCG 2D vs PyAMG SA-CG, setup incl. (1e-8)", "kinema-mgpcg", "pyamg", (n2,) * 2, 1e-8, 5.0),
        Target("cholesky factor+solve vs CHOLMOD/scikit-sparse (within 10%)", "kinema-cholesky", "cholmod",
               (n2,) * 2, None, 1 / 1.1),
        Target("cholesky factor+solve vs SciPy spsolve", "kinema-cholesky", "spsolve", (n2,) * 2, None, 3.0),
    ]


# ------------------------------------------------------------------ kinema adapters


def kinema_has(attribute: str) -> bool:
    """True when `kinema.<attribute>` (dotted) exists in the installed kinema."""
    try:
        import kinema

        obj = kinema
        for part in attribute.split("."):
            obj = getattr(obj, part)
        return True
    except (ImportError, AttributeError):
        return False


def kinema_poisson(f: np.ndarray, h: float, tol: float, matrix, method: str = "mgpcg") -> peers.PeerResult:
    """km.poisson.solve(f, h, bc="dirichlet", method=method, tol=tol), verified against `matrix`.

    Phases: 'solve' (the call, numpy in to numpy out), 'reported' (SolveInfo.seconds).
    """
    import time

    import kinema as km

    start = time.perf_counter()
    u, info = km.poisson.solve(f, h, bc="dirichlet", method=method, tol=tol)
    seconds = time.perf_counter() - start
    residual = peers.relative_residual(matrix, u, f)
    bound = peers.DIRECT_RESIDUAL_BOUND if method == "cholmod" else peers.ITERATIVE_SLACK * tol
    if not residual <= bound:
        raise peers.VerificationError(f"kinema {method}: relative residual {residual:.3e} exceeds {bound:.3e} "
                                      f"(kinema reported {info.residual:.3e})")
    return peers.PeerResult(u, {"solve": seconds, "total": seconds, "reported": info.seconds},
                            info.iterations, residual)


def kinema_cholesky(matrix, b: np.ndarray) -> peers.PeerResult:
    """km.sparse.cholesky(A) then Factor.solve(b), verified. Phases: 'factor' (analyse + factor), 'solve'."""
    import time

    import kinema as km

    start = time.perf_counter()
    factor = km.sparse.cholesky(matrix)
    factorise = time.perf_counter() - start
    start = time.perf_counter()
    x = factor.solve(b)
    solve = time.perf_counter() - start
    residual = peers.relative_residual(matrix, x, b)
    if not residual <= peers.DIRECT_RESIDUAL_BOUND:
        raise peers.VerificationError(f"kinema cholesky: relative residual {residual:.3e} exceeds "
                                      f"{peers.DIRECT_RESIDUAL_BOUND:.3e}")
    return peers.PeerResult(x, {"factor": factorise, "solve": solve, "total": factorise + solve}, None, residual)


# ------------------------------------------------------------------ problems and methods


class Problem:
    """One grid's right-hand side and operator, built once and shared by every method."""

    def __init__(self, shape):
        self.shape = tuple(shape)
        self.h = 1.0 / self.shape[0]
        self.f = peers.poisson_rhs(self.shape, self.h, kind="random")
        self.matrix = peers.laplacian_matrix(self.shape, self.h, bc="dirichlet")
        self._taichi = None
        self.taichi_first_solve = None

    def taichi(self, threads: int, tol: float) -> peers.TaichiMGPCG:
        """This grid's TaichiMGPCG, made once; its first solve (JIT compilation) is timed apart."""
        if self._taichi is None:
            solver = peers.TaichiMGPCG(self.shape, threads=threads)
            _, _, self.taichi_first_solve = solver.solve(self.h ** 2 * self.f, tol)
            self._taichi = solver
        return self._taichi


def method_runner(method: str, problem: Problem, tol: Optional[float], threads: int
                  ) -> tuple[Callable[[], peers.PeerResult], str]:
    """A zero-argument call solving `problem` with `method`, and the phase that is its figure."""
    if method.startswith("kinema-"):
        name = method[len("kinema-"):]
        if name == "cholesky":
            return (lambda: kinema_cholesky(problem.matrix, problem.f.ravel())), "total"
        return (lambda: kinema_poisson(problem.f, problem.h, tol, problem.matrix, name)), "total"
    if method == "pyamg":
        return (lambda: peers.pyamg_sa_cg(problem.matrix, problem.f, tol)), "total"
    if method == "spsolve":
        return (lambda: peers.scipy_spsolve(problem.matrix, problem.f)), "total"
    if method == "cholmod":
        return (lambda: peers.sksparse_cholmod(problem.matrix, problem.f, threads=threads)), "total"
    if method == "taichi":
        def run():
            solver = problem.taichi(threads, tol)
            b = problem.h ** 2 * problem.f
            x, iterations, seconds = solver.solve(b, tol)
            residual = float(np.linalg.norm(b - peers.taichi_operator(x)) / np.linalg.norm(b))
            if not residual <= peers.ITERATIVE_SLACK * tol:
                raise peers.VerificationError(f"taichi: relative residual {residual:.3e} exceeds "
                                              f"{peers.ITERATIVE_SLACK * tol:.3e}")
            phases = {"first_solve": problem.taichi_first_solve, "solve": seconds}
            return peers.PeerResult(x, phases, iterations, residual)
        return run, "solve"
    raise ValueError(f"method: unknown {method!r}")


def available(method: str) -> bool:
    """Whether `method` can run in this environment (kinema's solvers may not be built yet)."""
    if method == "kinema-cholesky":
        return kinema_has("sparse.cholesky")
    if method.startswith("kinema-"):
        return kinema_has("poisson.solve")
    return True


def thread_count(method: str, threads: int) -> int:
    """Threads a method really uses: PyAMG and SuperLU are serial."""
    return 1 if method in ("pyamg", "spsolve") else threads


# ------------------------------------------------------------------ runs


def time_method(method: str, problem: Problem, tol: Optional[float], args, min_of: int) -> harness.Measurement:
    """Times and verifies one method on one problem (raises when its result fails verification)."""
    run, phase = method_runner(method, problem, tol, args.threads)
    return harness.measure(run, min_of=min_of, max_tries=max(args.max_tries, min_of),
                           figure=lambda result, wall: result.seconds[phase])


def record_method(method: str, problem: Problem, tol: Optional[float], m: harness.Measurement, args,
                  recorder: harness.Recorder, *, error_reference: Optional[np.ndarray] = None,
                  benchmark_note: str = ""):
    """Records and prints one method's measurement; returns (Measurement, result)."""
    result = m.value
    error = result.residual
    notes = {"tol": tol if tol is not None else "direct", "residual": result.residual,
             **{f"t_{k}": v for k, v in result.seconds.items()}}
    if error_reference is not None:
        error = float(np.linalg.norm(result.solution.ravel() - error_reference.ravel())
                      / np.linalg.norm(error_reference))
        notes["error"] = "relative 2-norm error vs reference"
    if benchmark_note:
        notes["note"] = benchmark_note
    recorder.record(method, problem.shape, m.seconds, error=error, iterations=result.iterations,
                    threads=thread_count(method, args.threads), measurement=m, notes=notes)
    print(f"  {method:18s} {m.seconds:9.3f} s  iterations {result.iterations}  residual {result.residual:.2e}"
          f"  other_load {m.other_load:.2f}{' DISTURBED' if m.disturbed else ''}  repeats {m.repeats}", flush=True)
    return m, result


def measure_method(method: str, problem: Problem, tol: Optional[float], args, recorder: harness.Recorder,
                   *, error_reference: Optional[np.ndarray] = None, benchmark_note: str = ""):
    """Measures, verifies and records one method on one problem; returns (Measurement, result) or None."""
    try:
        m = time_method(method, problem, tol, args, args.min_of)
    except (peers.VerificationError, RuntimeError) as error:  # kinema's errors derive from RuntimeError
        print(f"  {method:18s} FAILED: {type(error).__name__}: {error}")
        return None
    return record_method(method, problem, tol, m, args, recorder, error_reference=error_reference,
                         benchmark_note=benchmark_note)


def measure_alternated(methods, problem: Problem, tol: Optional[float], args, recorder: harness.Recorder):
    """Measures several methods on one problem in args.min_of rounds, one call of each per round
    (A B A B ...), and records each method's best undisturbed call: a drift of the machine's
    speed over minutes then cannot favour the method measured first. Returns {method:
    Measurement or None (failed)}."""
    taken = {method: [] for method in methods}
    failed = set()
    for _ in range(args.min_of):
        for method in methods:
            if method in failed:
                continue
            try:
                taken[method].append(time_method(method, problem, tol, args, 1))
            except (peers.VerificationError, RuntimeError) as error:
                print(f"  {method:18s} FAILED: {type(error).__name__}: {error}")
                failed.add(method)
    return {method: None if method in failed else
            record_method(method, problem, tol, harness.combine(taken[method]), args, recorder)[0]
            for method in methods}


def run_targets(args) -> int:
    """Measures every target's pair once (shared between targets) and prints the ratios."""
    recorder = harness.Recorder(OUT / "side_by_side.csv", benchmark="side_by_side", threads=args.threads)
    print(f"commit {recorder.commit}, threads {args.threads}, BLAS: {peers.blas_description()}")
    problems: dict = {}
    figures: dict = {}
    failures = 0
    for target in targets(args.quick):
        if args.only and not any(word.lower() in target.name.lower() for word in args.only):
            continue
        print(f"{target.name}: {harness.format_size(target.shape)}")
        problem = problems.setdefault(target.shape, Problem(target.shape))
        pair = [method for method in (target.ours, target.peer)
                if (method, target.shape, target.tol) not in figures and available(method)]
        if args.alternate and len(pair) == 2:
            for method, m in measure_alternated(pair, problem, target.tol, args, recorder).items():
                figures[(method, target.shape, target.tol)] = m
                failures += m is None
        for method in (target.ours, target.peer):
            key = (method, target.shape, target.tol)
            if key in figures:
                continue
            if not available(method):
                print(f"  {method:18s} skipped: not in the installed kinema yet")
                figures[key] = None
                continue
            outcome = measure_method(method, problem, target.tol, args, recorder)
            figures[key] = None if outcome is None else outcome[0]
            failures += outcome is None
        ours = figures[(target.ours, target.shape, target.tol)]
        theirs = figures[(target.peer, target.shape, target.tol)]
        if ours is not None and theirs is not None:
            ratio = theirs.seconds / ours.seconds
            verdict = "meets" if ratio >= target.ratio else "MISSES"
            print(f"  -> ratio {ratio:.2f} (target >= {target.ratio:.2f}): {verdict}")
    return failures


def run_sweeps(args) -> int:
    """Work-precision sweeps: every iterative method over SWEEP_TOLS, error against a reference."""
    recorder = harness.Recorder(OUT / "work_precision.csv", benchmark="work_precision", threads=args.threads)
    failures = 0
    shapes = [(32,) * 3, (128,) * 2] if args.quick else [(128,) * 3, (1024,) * 2]
    for shape in shapes:
        problem = Problem(shape)
        size = harness.format_size(shape)
        print(f"work-precision {size}: references to {REFERENCE_TOL:g} (PyAMG SA-CG, independent of kinema)")
        reference = peers.pyamg_sa_cg(problem.matrix, problem.f, REFERENCE_TOL).solution
        taichi_reference = peers.pyamg_sa_cg(peers.laplacian_matrix(shape, 1.0, bc="dirichlet_vertex"),
                                             problem.h ** 2 * problem.f, REFERENCE_TOL).solution
        methods = ["pyamg", "taichi"] + [f"kinema-{m}" for m in SWEEP_KINEMA_METHODS]
        for method in methods:
            if not available(method):
                print(f"  {method:18s} skipped: not in the installed kinema yet")
                continue
            for tol in SWEEP_TOLS:
                ref = taichi_reference if method == "taichi" else reference
                failures += measure_method(method, problem, tol, args, recorder, error_reference=ref) is None
        for method in ("cholmod", "kinema-cholesky") if len(shape) == 2 else ():
            if available(method):
                failures += measure_method(method, problem, None, args, recorder, error_reference=reference) is None
        plot = harness.plot_work_precision(recorder.path, OUT / f"work_precision_{size}.png",
                                           benchmark="work_precision", size=size)
        print(f"  plot: {plot}")
    return failures


def run_stream(args) -> None:
    """STREAM triad (bench/cpp/bench_stream.cpp) and, in the same program run, kinema's stencil
    apply and red-black sweep (bench/cpp/bench_grid.cpp): their bandwidth as a share of the triad's.
    The repetitions of all of them run interleaved in random order, best of 8 each."""
    if not BENCH_BINARY.exists():
        print(f"stream: {BENCH_BINARY} missing; build it with cmake -S . -B build/bench "
              "-DKINEMA_BUILD_BENCH=ON -DKINEMA_BUILD_PYTHON=OFF && cmake --build build/bench -j2")
        return
    recorder = harness.Recorder(OUT / "stream.csv", benchmark="stream_triad", threads=args.threads)
    m = harness.run_google_benchmark(BENCH_BINARY, "StreamTriad|PoissonApply(Baseline)?/|RedBlackSweep/",
                                     repetitions=8, interleave=True, max_tries=args.max_tries)
    # The cached-store triad is the reference; the non-temporal one (no write-allocate)
    # is the fair ceiling for the 3D apply, which streams its result on large grids.
    triad = {}
    for variant, label in (("StreamTriad", "STREAM triad"), ("StreamTriadNT", "STREAM triad, non-temporal stores")):
        rows_of = [b for b in m.value if b["name"].startswith(f"BM_{variant}/")]
        for threads in sorted({int(b["threads"]) for b in rows_of}):
            rows = [b for b in rows_of if int(b["threads"]) == threads]
            best = max(rows, key=lambda b: b["GB"])
            triad[variant, threads] = best["bytes_per_second"]
            recorder.record("triad" if variant == "StreamTriad" else "triad_nt", "3x80MiB",
                            best["real_time"] * 1e-3, threads=threads, measurement=m,
                            notes={"GB/s": best["GB"], "GB/s_bus": best["GB_write_alloc"],
                                   "repetitions": len(rows)})
            print(f"{label}, {threads} thread(s): {best['GB']:.1f} GB/s "
                  f"({best['GB_write_alloc']:.1f} GB/s on the bus), other_load {m.other_load:.2f}")
    for kernel in ("PoissonApply", "PoissonApplyBaseline", "RedBlackSweep"):
        for size in ("2/1024", "3/128", "3/256"):
            rows = [b for b in m.value if b["name"].startswith(f"BM_{kernel}/{size}/")]
            if not rows:
                continue
            best = max(rows, key=lambda b: b["bytes_per_second"])
            threads = int(best["threads"])
            share = best["bytes_per_second"] / triad.get(("StreamTriad", threads), float("nan"))
            share_nt = best["bytes_per_second"] / triad.get(("StreamTriadNT", threads), float("nan"))
            recorder.record(kernel, size.replace("/", "D "), best["real_time"] * 1e-3, threads=threads,
                            measurement=m, notes={"GB/s": best["bytes_per_second"] / 1e9, "share_of_triad": share,
                                                  "share_of_triad_nt": share_nt})
            print(f"{kernel:20s} {size.replace('/', 'D '):>8}: {best['real_time']:.3f} ms, "
                  f"{best['bytes_per_second'] / 1e9:.1f} GB/s = {100 * share:.0f}% of the triad, "
                  f"{100 * share_nt:.0f}% of the non-temporal triad ({threads} threads)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small grids (32^3, 128^2): a wiring check")
    parser.add_argument("--sweep", action="store_true", help="also the work-precision sweeps")
    parser.add_argument("--stream", action="store_true", help="also the STREAM triad")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--min-of", type=int, default=1, help="undisturbed timed calls to keep the best of")
    parser.add_argument("--alternate", action="store_true",
                        help="time each target's two codes in alternation, one call each per round, "
                             "--min-of rounds (instead of all calls of one code, then the other's)")
    parser.add_argument("--max-tries", type=int, default=5, help="timed calls at most when disturbed")
    parser.add_argument("--only", nargs="+", metavar="WORD",
                        help="only the targets whose name holds one of these words (e.g. cholesky)")
    args = parser.parse_args(argv)
    if kinema_has("set_num_threads"):
        import kinema

        kinema.set_num_threads(args.threads)
    if args.stream:
        run_stream(args)
    failures = run_targets(args)
    if args.sweep:
        failures += run_sweeps(args)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
