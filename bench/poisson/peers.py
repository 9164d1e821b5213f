"""Peer solvers for kinema's side-by-side benchmarks, each timed by phase and verified here.

Every peer returns a PeerResult (solution, seconds by phase, iterations, residual) and computes
the relative residual ||b - A x||_2 / ||b||_2 of its answer itself, with its own operator,
raising VerificationError when the answer misses the requested accuracy: a fast wrong answer
must not become a figure. That residual is the same quantity as kinema's SolveInfo.residual.

Peers (all called through their installed packages, none of their code is copied here):
- pyamg_sa_cg: PyAMG smoothed aggregation (Vanek, Mandel and Brezina 1996) as the
  preconditioner of CG; setup (the hierarchy) and solve timed separately.
- scipy_spsolve: SciPy's sparse direct solver (SuperLU, COLAMD ordering by default).
- sksparse_cholmod: CHOLMOD (Chen, Davis, Hager and Rajamanickam 2008) through scikit-sparse;
  analyse, factor and solve timed separately.
- taichi_mgpcg / TaichiMGPCG: the MGPCG class bundled with the taichi wheel
  (taichi/examples/algorithm/mgpcg_advanced.py), on Taichi's CPU backend in float64; the first
  solve (which JIT-compiles every kernel) and a second, steady-state solve timed separately.
  What it solves is stated in TaichiMGPCG's docstring and in TAICHI_OPERATOR below.

The matrix peers take the cell-centred Laplacian of laplacian_matrix(), the operator of
km.poisson with the same C-order unknown numbering as ``f.ravel()``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import time
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import numpy as np
import scipy.sparse as sp

#: Residual below which a direct solve counts as exact (relative 2-norm; a backward-stable
#: factorisation of these operators lands near 1e-15).
DIRECT_RESIDUAL_BOUND = 1e-10
#: An iterative peer passes verification when its true residual is below SLACK * tol: the
#: recursively updated residual a solver stops on drifts from the true one by rounding only.
ITERATIVE_SLACK = 2.0

#: What Taichi's bundled MGPCG solves, for reports (see TaichiMGPCG).
TAICHI_OPERATOR = (
    "(A x)_I = 2d x_I - sum of the 2d neighbours x_{I+-e_k}, on N^d unknowns, x = 0 outside the "
    "block: -h^2 lap with homogeneous Dirichlet values at the first cell centres outside "
    "(vertex-centred, boundary at distance h), not kinema's ghost = -u (boundary at h/2)"
)


class VerificationError(AssertionError):
    """A peer's answer failed its own residual check."""


class PeerResult(NamedTuple):
    """One peer solve.

    solution: the answer, shaped like the right-hand side given.
    seconds: wall time by phase [s], e.g. {'setup': .., 'solve': .., 'total': ..}.
    iterations: Krylov iterations (None for direct solvers).
    residual: relative residual ||b - A x||_2 / ||b||_2, computed here.
    """

    solution: np.ndarray
    seconds: dict
    iterations: Optional[int]
    residual: float


# ------------------------------------------------------------------ problems


def laplacian_matrix(shape: Sequence[int], h: float, bc: str = "dirichlet") -> sp.csr_matrix:
    """The cell-centred 5-point (2D) / 7-point (3D) operator A = -lap on a grid of `shape`, spacing h.

    Unknowns are numbered in C order, as ``f.ravel()`` of an array indexed [i, j(, k)] = x, y(, z).
    Each face of a cell contributes to its row, divided by h^2:
    - an interior face: +1 on the diagonal, -1 for the neighbour across it;
    - a boundary face with bc="dirichlet": u = 0 on the face via the ghost value -u, so
      (u - (-u)) / h^2 = +2 on the diagonal;
    - a boundary face with bc="neumann": nothing (zero flux); the matrix is then singular
      with the constants as null space;
    - a boundary face with bc="dirichlet_vertex": +1 on the diagonal, u = 0 one full spacing
      out (vertex-centred Dirichlet); with h = 1 this is the operator of Taichi's MGPCG.
    So a Dirichlet corner cell in 2D has diagonal (1 + 1 + 2 + 2) / h^2 = 6 / h^2.
    With bc in {"dirichlet", "neumann"} this is km.poisson.matrix(shape, h, bc) without
    solids, built independently of kinema.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) not in (2, 3) or min(shape) < 1:
        raise ValueError(f"shape: expected 2 or 3 positive sizes, got {shape}")
    if not h > 0:
        raise ValueError(f"h: expected a positive spacing, got {h}")
    boundary_face = {"dirichlet": 2.0, "neumann": 0.0, "dirichlet_vertex": 1.0}
    if bc not in boundary_face:
        raise ValueError(f"bc: expected one of {sorted(boundary_face)}, got {bc!r}")
    inv_h2 = 1.0 / (h * h)
    count = int(np.prod(shape))
    index = np.arange(count, dtype=np.int64).reshape(shape)
    diagonal = np.zeros(shape)
    rows, cols = [], []
    for axis, n in enumerate(shape):
        # Faces between cell c and c + e_axis.
        lower = index[tuple(slice(0, n - 1) if a == axis else slice(None) for a in range(len(shape)))].ravel()
        upper = index[tuple(slice(1, n) if a == axis else slice(None) for a in range(len(shape)))].ravel()
        rows += [lower, upper]
        cols += [upper, lower]
        faces = np.full(n, 2.0)  # interior faces per cell along this axis
        faces[0] -= 1.0
        faces[-1] -= 1.0
        faces[0] += boundary_face[bc]
        faces[-1] += boundary_face[bc]
        diagonal += faces.reshape([n if a == axis else 1 for a in range(len(shape))])
    rows = np.concatenate(rows + [np.arange(count)])
    cols = np.concatenate(cols + [np.arange(count)])
    values = np.concatenate([np.full(rows.size - count, -inv_h2), diagonal.ravel() * inv_h2])
    matrix = sp.csr_matrix((values, (rows, cols)), shape=(count, count))
    matrix.sum_duplicates()
    matrix.sort_indices()
    return matrix


def poisson_rhs(shape: Sequence[int], h: float, kind: str = "random", seed: int = 0) -> np.ndarray:
    """A right-hand side f for -lap u = f on the cell-centred grid of `shape`, spacing h.

    kind="random": uniform in [-1, 1) with a fixed seed; every eigenmode is excited, the hard
    case for iterative solvers and the default for speed comparisons.
    kind="smooth": f = sum_k (pi/L_k)^2 * prod_k sin(pi x_k / L_k) at the cell centres
    x_k = (i_k + 1/2) h, L_k = n_k h, whose continuous Dirichlet solution is the product of sines.
    """
    shape = tuple(int(n) for n in shape)
    if kind == "random":
        return np.random.default_rng(seed).uniform(-1.0, 1.0, size=shape)
    if kind == "smooth":
        f = np.ones(shape)
        wave = 0.0
        for axis, n in enumerate(shape):
            length = n * h
            x = (np.arange(n) + 0.5) * h
            f = f * np.sin(np.pi * x / length).reshape([n if a == axis else 1 for a in range(len(shape))])
            wave += (np.pi / length) ** 2
        return wave * f
    raise ValueError(f"kind: expected 'random' or 'smooth', got {kind!r}")


def relative_residual(matrix, x: np.ndarray, b: np.ndarray) -> float:
    """||b - A x||_2 / ||b||_2 (the absolute residual when b = 0)."""
    b = np.ravel(b)
    r = b - matrix @ np.ravel(x)
    norm_b = np.linalg.norm(b)
    return float(np.linalg.norm(r) / (norm_b if norm_b > 0 else 1.0))


def _check(name: str, residual: float, bound: float) -> None:
    if not np.isfinite(residual) or residual > bound:
        raise VerificationError(f"{name}: relative residual {residual:.3e} exceeds the bound {bound:.3e}")


def blas_description() -> str:
    """The BLAS/OpenMP libraries loaded in this process and their thread counts (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    parts = []
    for lib in threadpool_info():
        name = lib.get("internal_api", "?")
        version = lib.get("version") or ""
        layer = lib.get("threading_layer")
        path = Path(lib.get("filepath", "")).name
        parts.append(f"{name} {version}{'/' + layer if layer else ''} ({path}, {lib.get('num_threads')} threads)")
    return ", ".join(parts)


def _thread_limits(threads: Optional[int]):
    """Limits every BLAS/OpenMP pool to `threads` for the block (no-op when None)."""
    if threads is None:
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(threads))


# ------------------------------------------------------------------ matrix peers


def pyamg_sa_cg(matrix, b: np.ndarray, tol: float = 1e-8, *, max_iter: int = 500,
                threads: Optional[int] = 1) -> PeerResult:
    """CG preconditioned by one PyAMG smoothed-aggregation V-cycle, from x0 = 0, to ||r|| < tol ||b||.

    PyAMG's defaults otherwise (symmetric strength, symmetric Gauss-Seidel smoothing, so the
    preconditioner is SPD). Phases: 'setup' (the aggregation hierarchy), 'solve'; iterations
    are CG iterations (each one V-cycle). PyAMG's kernels are serial; numpy's BLAS only runs its
    vector operations, where a second thread adds wake-up costs and, on a loaded machine, made
    the setup 5 to 15 times slower (32^3: 0.15 s with 1 thread, 0.7-2.5 s with 2). So BLAS is
    limited to `threads` = 1 by default (None leaves it alone).
    """
    import pyamg

    b = np.ravel(np.asarray(b, dtype=np.float64))
    matrix = sp.csr_matrix(matrix)
    with _thread_limits(threads):
        start = time.perf_counter()
        hierarchy = pyamg.smoothed_aggregation_solver(matrix)
        setup = time.perf_counter() - start
        residuals: list = []
        start = time.perf_counter()
        x = hierarchy.solve(b, x0=np.zeros_like(b), tol=tol, maxiter=max_iter, accel="cg", residuals=residuals)
        solve = time.perf_counter() - start
    residual = relative_residual(matrix, x, b)
    _check("pyamg_sa_cg", residual, ITERATIVE_SLACK * tol)
    return PeerResult(x, {"setup": setup, "solve": solve, "total": setup + solve}, len(residuals) - 1, residual)


def scipy_spsolve(matrix, b: np.ndarray, *, permc_spec: str = "COLAMD",
                  threads: Optional[int] = 1) -> PeerResult:
    """scipy.sparse.linalg.spsolve (SuperLU, no UMFPACK) with the column ordering `permc_spec`.

    SciPy's default is COLAMD, which ignores symmetry; "MMD_AT_PLUS_A" is the better choice
    for a symmetric matrix. The matrix is converted to CSC before the clock starts (SuperLU's
    format), as any caller would do once. Phase: 'solve' (ordering + factor + solve).
    SuperLU is serial; BLAS is limited to `threads` = 1 by default, as for PyAMG.
    """
    from scipy.sparse.linalg import spsolve

    b = np.ravel(np.asarray(b, dtype=np.float64))
    csc = sp.csc_matrix(matrix)
    with _thread_limits(threads):
        start = time.perf_counter()
        x = spsolve(csc, b, permc_spec=permc_spec, use_umfpack=False)
        solve = time.perf_counter() - start
    residual = relative_residual(csc, x, b)
    _check("scipy_spsolve", residual, DIRECT_RESIDUAL_BOUND)
    return PeerResult(x, {"solve": solve, "total": solve}, None, residual)


def sksparse_cholmod(matrix, b: np.ndarray, *, mode: str = "supernodal", ordering: str = "default",
                     threads: Optional[int] = None) -> PeerResult:
    """CHOLMOD through scikit-sparse: analyse (fill-reducing ordering), factor, solve.

    mode="supernodal" is the method km.sparse.cholesky uses; ordering="default" is CHOLMOD's
    own choice (AMD, then METIS/NESDIS if AMD fills too much). Supernodal CHOLMOD spends its
    time in the BLAS of the system's libblas.so.3 (Debian alternatives), limited to `threads`.
    The matrix is handed over as CSC (CHOLMOD's format) converted before the clock starts.
    Phases: 'analyse', 'factor', 'solve', 'total'.
    """
    from sksparse.cholmod import analyze

    b = np.ravel(np.asarray(b, dtype=np.float64))
    csc = sp.csc_matrix(matrix)
    with _thread_limits(threads):
        start = time.perf_counter()
        factor = analyze(csc, mode=mode, ordering_method=ordering)
        analyse = time.perf_counter() - start
        start = time.perf_counter()
        factor.cholesky_inplace(csc)
        factorise = time.perf_counter() - start
        start = time.perf_counter()
        x = factor(b)
        solve = time.perf_counter() - start
    residual = relative_residual(csc, x, b)
    _check("sksparse_cholmod", residual, DIRECT_RESIDUAL_BOUND)
    seconds = {"analyse": analyse, "factor": factorise, "solve": solve, "total": analyse + factorise + solve}
    return PeerResult(x, seconds, None, residual)


# ------------------------------------------------------------------ Taichi MGPCG


def taichi_operator(x: np.ndarray) -> np.ndarray:
    """Applies the operator of Taichi's MGPCG (TAICHI_OPERATOR) to a 2D/3D array with numpy."""
    padded = np.pad(x, 1)
    result = 2 * x.ndim * x
    inner = tuple(slice(1, -1) for _ in range(x.ndim))
    for axis in range(x.ndim):
        for shift in (-1, 1):
            window = list(inner)
            window[axis] = slice(1 + shift, padded.shape[axis] - 1 + shift)
            result = result - padded[tuple(window)]
    return result


def taichi_default_levels(n: int) -> int:
    """Multigrid levels giving a 16-cell coarsest grid: Taichi's own example uses 4 levels at N = 128."""
    return max(1, int(np.log2(n // 16)) + 1) if n >= 16 else 1


def _taichi_mgpcg_module():
    """Imports taichi/examples/algorithm/mgpcg_advanced.py from the installed taichi wheel."""
    import taichi

    path = Path(taichi.__file__).parent / "examples" / "algorithm" / "mgpcg_advanced.py"
    if not path.is_file():
        raise ImportError(f"taichi {taichi.__version__} ships no {path}")
    spec = importlib.util.spec_from_file_location("taichi_example_mgpcg_advanced", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # defines the classes only; its demo sits behind __main__
    return module


class TaichiMGPCG:
    """Taichi's bundled MGPCG on its CPU backend in float64, for N^d right-hand sides.

    What is solved (read from the installed mgpcg_advanced.py, Taichi 1.7):
    - A is TAICHI_OPERATOR: (A x)_I = 2d x_I - sum_k (x_{I+e_k} + x_{I-e_k}) on the N^d block,
      which sits at offset N/2 inside a sparse (pointer) grid of extent 2N; cells outside the
      block are inactive and read as 0. That is -h^2 lap with u = 0 at the first cell centres
      outside, a vertex-centred Dirichlet problem, unscaled: laplacian_matrix(shape, 1.0,
      bc="dirichlet_vertex"). kinema's cell-centred operator (ghost = -u) differs only in the
      boundary rows (diagonal 2d + 1 per boundary face instead of 2d): same unknown count, same
      stencil, same O(h^-2) conditioning. To pose -lap u = f at spacing h, pass b = h^2 f; the
      relative residual does not change with that scaling.
    - Preconditioner: one V-cycle, red-black Gauss-Seidel with 2 << l sweeps before and after
      on level l, 50 sweeps on the coarsest, restriction 0.5 x (sum of the 2^d children),
      piecewise-constant prolongation, the same unscaled stencil on every level.
    - Stopping: after each CG update, ||r||^2 < max(abs_tol, rel_tol * ||r_0||^2) with the
      recursively updated r and r_0 = b (x0 = 0). So the 2-norm relative residual tol here is
      rel_tol = tol^2 with abs_tol = 0. (The class's default rel_tol = 1e-12 is tol = 1e-6.)
      Its default eps = 1e-12, added to both CG denominators, is not scale-invariant and would
      distort beta near convergence for b = h^2 f, so eps = 0 is passed (b = 0 is answered
      with x = 0 without calling Taichi).
    - Precision: ti.init(arch=ti.cpu, default_fp=ti.f64) and MGPCG(real=ti.f64).

    shape: (N, N) or (N, N, N), N a power of two >= 8.
    threads: Taichi's CPU thread pool size (cpu_max_num_threads; default: all CPUs).
    n_mg_levels: default taichi_default_levels(N) (16 cells on the coarsest level, as the
    example's 4 levels at N = 128).
    offline_cache: Taichi's on-disk kernel cache; off so that a first solve includes the JIT.
    Construction calls ti.init, which resets Taichi's runtime: a previously made TaichiMGPCG
    (or any Taichi field) is unusable afterwards, so keep one alive at a time.
    setup_seconds: time of ti.init and field allocation [s].
    """

    def __init__(self, shape: Sequence[int], *, threads: Optional[int] = None,
                 n_mg_levels: Optional[int] = None, offline_cache: bool = False):
        shape = tuple(int(s) for s in shape)
        n = shape[0]
        if len(shape) not in (2, 3) or any(s != n for s in shape):
            raise ValueError(f"shape: expected a square or cubic 2D/3D grid, got {shape}")
        if n < 8 or n & (n - 1):
            raise ValueError(f"shape: Taichi's MGPCG needs N a power of two >= 8, got N = {n}")
        import taichi as ti

        module = _taichi_mgpcg_module()
        start = time.perf_counter()
        ti.init(arch=ti.cpu, default_fp=ti.f64, cpu_max_num_threads=int(threads or os.cpu_count() or 1),
                offline_cache=offline_cache, log_level=ti.WARN)
        self.shape = shape
        self.levels = taichi_default_levels(n) if n_mg_levels is None else int(n_mg_levels)
        self._solver = module.MGPCG(dim=len(shape), N=n, n_mg_levels=self.levels, real=ti.f64)
        self._rhs = ti.field(dtype=ti.f64, shape=shape)
        self._out = ti.field(dtype=ti.f64, shape=shape)
        self.setup_seconds = time.perf_counter() - start

    def solve(self, b: np.ndarray, tol: float = 1e-6, max_iter: int = 1000):
        """Solves A x = b from x0 = 0 to ||b - A x|| <= tol ||b||; returns (x, iterations, seconds).

        seconds covers numpy b in to numpy x out. iterations are CG iterations (one V-cycle
        each), counted from the solver's verbose per-iteration lines. Not verified here.
        """
        b = np.ascontiguousarray(b, dtype=np.float64)
        if b.shape != self.shape:
            raise ValueError(f"b: expected shape {self.shape}, got {b.shape}")
        if not np.any(b):
            return np.zeros_like(b), 0, 0.0
        start = time.perf_counter()
        self._rhs.from_numpy(b)
        self._solver.init(self._rhs, 1.0)
        log = io.StringIO()
        with contextlib.redirect_stdout(log):
            self._solver.solve(max_iters=max_iter, eps=0.0, abs_tol=0.0, rel_tol=tol * tol, verbose=True)
        self._solver.get_result(self._out)
        x = self._out.to_numpy()
        seconds = time.perf_counter() - start
        return x, sum(line.startswith("iter ") for line in log.getvalue().splitlines()), seconds


def taichi_mgpcg(b: np.ndarray, tol: float = 1e-6, *, threads: Optional[int] = None,
                 n_mg_levels: Optional[int] = None, max_iter: int = 1000,
                 offline_cache: bool = False) -> PeerResult:
    """Solves A x = b with a fresh TaichiMGPCG twice: the first solve JIT-compiles, the second is timed.

    A is TAICHI_OPERATOR (see TaichiMGPCG for exactly what Taichi solves and how tol maps to
    its stopping test). Phases: 'setup' (ti.init, fields), 'first_solve' (including JIT
    compilation of every kernel), 'solve' (the same solve again: steady state, the figure to
    compare). iterations and the verified residual are those of the steady-state solve.
    """
    solver = TaichiMGPCG(np.shape(b), threads=threads, n_mg_levels=n_mg_levels, offline_cache=offline_cache)
    _, _, first = solver.solve(b, tol, max_iter)
    x, iterations, steady = solver.solve(b, tol, max_iter)
    b = np.asarray(b, dtype=np.float64)
    norm_b = np.linalg.norm(b)
    residual = float(np.linalg.norm(b - taichi_operator(x)) / (norm_b if norm_b > 0 else 1.0))
    _check("taichi_mgpcg", residual, ITERATIVE_SLACK * tol)
    seconds = {"setup": solver.setup_seconds, "first_solve": first, "solve": steady}
    return PeerResult(x, seconds, iterations, residual)
