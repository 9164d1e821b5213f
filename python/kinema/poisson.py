"""Poisson's equation on cell-centred grids: -lap(u) = f in 2D and 3D.

The operator is the standard 5-point (2D) or 7-point (3D) finite-volume Laplacian on the grid
of ``f.shape`` with spacing ``h`` (cell ``(i, j)`` centred at ``((i+0.5)h, (j+0.5)h)``):

* ``bc="dirichlet"``: u = 0 on the domain's boundary faces (ghost cell = -u);
* ``bc="neumann"``: zero normal derivative on every boundary face; f must integrate to zero
  (per connected fluid region) and the returned u has zero mean there;
* ``bc="periodic"``: every axis wraps around (cell n-1 neighbours cell 0); singular like
  Neumann (f must have zero mean, u is returned with zero mean). The red-black methods
  (gauss_seidel, multigrid, mgpcg) need an even number of cells per axis;
* ``solid``: a bool mask of cells excluded from the domain; their faces carry no flux and u is
  0 in them.

Methods: ``"jacobi"`` (damped, omega = 0.8), ``"gauss_seidel"`` (red-black), ``"cg"``
(Jacobi-preconditioned conjugate gradients), ``"multigrid"`` (V(2,2)-cycles),
``"mgpcg"`` (CG preconditioned by one V-cycle, McAdams, Sifakis & Teran 2010) and
``"cholmod"`` (sparse Cholesky through :func:`kinema.sparse.cholesky`). All reach the same
discrete solution. :class:`Solver` keeps the multigrid hierarchy for repeated solves.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from kinema import _core
from kinema._checks import (
    as_float_array, choice, grid_array, grid_shape, integer, positive, positive_int, real, representable,
    simulation_object, spacing)
from kinema._info import SolveInfo
from kinema.errors import ConvergenceError, DivergenceError

__all__ = ["solve", "laplacian", "matrix", "Solver", "METHODS"]

METHODS = ("jacobi", "gauss_seidel", "cg", "multigrid", "mgpcg", "cholmod")
_BCS = ("dirichlet", "neumann", "periodic")

# Relative size of f's null-space component above which Neumann data counts as incompatible;
# rounding in a discrete divergence leaves ~1e-16, a sampled analytic f ~h^2.
_COMPATIBILITY_TOL = 1e-8


def _solid_mask(solid, shape):
    if solid is None:
        return None
    mask = np.asarray(solid)
    if mask.shape != tuple(shape):
        raise ValueError(f"solid: expected a bool array of shape {tuple(shape)}, got shape {mask.shape}")
    if mask.dtype != np.bool_:
        if not np.issubdtype(mask.dtype, np.integer) or not np.isin(mask, (0, 1)).all():
            raise ValueError(f"solid: expected a bool array, got dtype {mask.dtype}")
    return np.ascontiguousarray(mask, dtype=np.uint8)


@simulation_object
class Solver:
    """A reusable solver for ``(shift*I - lap) u = f`` on one grid, boundary and solid mask.

    Building it assembles the multigrid hierarchy (for "multigrid" and "mgpcg") or the sparse
    Cholesky factor ("cholmod") once; each :meth:`solve` then allocates nothing but its result.

    shape: (nx, ny[, nz]) cells. h: cell size [m]. bc: "dirichlet", "neumann" or "periodic".
    solid: optional bool mask of ``shape``. shift: diagonal shift >= 0 [1/m^2] (the implicit
    diffusion schemes use shift = 1/(kappa dt)). pre_smooth, post_smooth: red-black sweeps of
    the V-cycle.
    """

    def __init__(self, shape, h, bc="dirichlet", *, method="mgpcg", solid=None, shift=0.0,
                 pre_smooth=2, post_smooth=2):
        self.shape = grid_shape(shape, "shape")
        self.h = spacing(h, "h")
        self.bc = choice(bc, "bc", _BCS)
        self.method = choice(method, "method", METHODS)
        shift = real(shift, "shift")
        if not np.isfinite(shift) or shift < 0:
            raise ValueError(f"shift: expected a finite number >= 0, got {shift}")
        self.shift = shift
        mask = _solid_mask(solid, self.shape)
        config = _core.poisson.Config()
        config.method = getattr(_core.poisson.Method, "cg" if method == "cholmod" else method)
        config.pre_smooth = integer(pre_smooth, "pre_smooth", low=0, high=64)
        config.post_smooth = integer(post_smooth, "post_smooth", low=0, high=64)
        self._core = _core.poisson.Solver(list(self.shape), self.h, getattr(_core.poisson.Boundary, bc), mask,
                                          shift, config)
        self._factor = None
        self._free = None
        if method == "cholmod":
            self._build_cholmod()

    @property
    def singular(self) -> bool:
        """True when the operator has a null space (Neumann or enclosed regions, no shift)."""
        return self._core.singular

    @property
    def levels(self) -> int:
        """Number of multigrid levels (1 for methods without a hierarchy)."""
        return self._core.levels

    def matrix(self) -> sp.csr_matrix:
        """The operator as a CSR matrix over all cells (rows of solid cells are empty)."""
        indptr, indices, data = self._core.assemble()
        n = int(np.prod(self.shape))
        return sp.csr_matrix((data, indices, indptr), shape=(n, n))

    def apply(self, u) -> np.ndarray:
        """A u for a cell array ``u`` of ``shape``."""
        u = self._cell_array(u, "u")
        return representable(self._core.apply(u), "u", "A u")

    def _cell_array(self, a, name):
        a = as_float_array(a, name)
        if a.shape != self.shape:
            raise ValueError(f"{name}: expected shape {self.shape}, got {a.shape}")
        return a

    def _build_cholmod(self):
        from kinema import sparse

        A = self.matrix()
        free = np.diff(A.indptr) > 0  # solid cells have empty rows
        # Pin one cell per singular component: the reduced matrix is then SPD, and projecting
        # afterwards restores the zero-mean gauge.
        free[self._core.anchor_cells()] = False
        self._free = np.flatnonzero(free)
        self._A = A
        self._factor = sparse.cholesky(A[self._free][:, self._free])

    def solve(self, f, *, tol=1e-8, max_iter=None, x0=None, rhs_mean="check",
              raise_on_failure=True):
        """Solves A u = f. Returns ``(u, SolveInfo)``.

        tol: relative residual ||f - A u|| / ||f|| to reach. max_iter: iteration cap (default
        from the method and grid size). x0: initial guess. rhs_mean (singular operators):
        "check" raises ValueError when f is not compatible (its mean per region is not ~0),
        "remove" removes it silently. raise_on_failure: raise km.ConvergenceError when tol is
        not reached (otherwise return the info with converged=False).
        """
        f = self._cell_array(f, "f")
        tol = positive(tol, "tol")
        max_iter = positive_int(max_iter, "max_iter", allow_none=True) or 0
        choice(rhs_mean, "rhs_mean", ("check", "remove"))
        if self.singular and rhs_mean == "check":
            bad = self._core.incompatibility(f)
            if bad > _COMPATIBILITY_TOL:
                raise ValueError(
                    f"f: incompatible with a pure-Neumann problem: its mean over the fluid "
                    f"region is {bad:.3g} times its mean magnitude (must be ~0, below "
                    f"{_COMPATIBILITY_TOL:g}); remove it or pass rhs_mean='remove'")
        if x0 is None:
            u = np.zeros(self.shape)
        else:
            u = self._cell_array(x0, "x0").copy()
        # The solvers' norms are sums of squares: for max |f| below ~1e-154 they underflow to 0
        # (u = 0 was returned as converged with residual 0) and above ~1e150 they overflow (a
        # representable solution was refused). The problem is linear: f and x0 are scaled by a
        # power of two (exact) into a safe range and u scaled back. Ordinary f is untouched.
        shift = 0  # f is scaled by 2^shift
        f_max = float(np.abs(f).max()) if f.size else 0.0
        if f_max > 0 and not 2.0**-450 < f_max < 2.0**450:
            shift = -int(np.frexp(f_max)[1])
            f = np.ldexp(f, shift)
            with np.errstate(over="ignore", under="ignore"):
                u = np.ldexp(u, shift)
            if not np.isfinite(u).all():
                u[...] = 0  # x0 beyond the range of this f: start from zero
        try:
            if self.method == "cholmod":
                info = self._solve_direct(f, u, tol)
            else:
                info = self._core.solve(f, u, tol, max_iter)
        except DivergenceError:
            # f and x0 are finite and the operator is definite: only overflow makes u non-finite
            raise ValueError(f"f: the solution overflows float64 (max |f| = {f_max:.3g}, "
                             f"h = {self.h:g}); scale f into a smaller range") from None
        if shift:
            with np.errstate(over="ignore", under="ignore"):
                u = np.ldexp(u, -shift)
        representable(u, "f", "the solution")
        if not info.converged and raise_on_failure:
            err = ConvergenceError(
                f"poisson ({self.method}): residual {info.residual:.3e} after {info.iterations} "
                f"iterations, above tol={tol:g}; raise max_iter or use method='mgpcg'")
            err.info = info
            raise err
        return u, info

    def _solve_direct(self, f, u, tol):
        import time

        t0 = time.perf_counter()
        b = f.ravel().copy()
        self._core.project(b.reshape(self.shape))
        x = np.zeros_like(b)
        b_norm = np.linalg.norm(b)
        refinements = 0
        x[self._free] = self._factor.solve(b[self._free])
        self._core.project(x.reshape(self.shape))
        r = b - self._A @ x
        self._core.project(r.reshape(self.shape))
        history = [1.0 if b_norm else 0.0]
        # Iterative refinement recovers accuracy lost to rounding on ill-conditioned grids.
        while b_norm and np.linalg.norm(r) > tol * b_norm and refinements < 3:
            x[self._free] += self._factor.solve(r[self._free])
            self._core.project(x.reshape(self.shape))
            r = b - self._A @ x
            self._core.project(r.reshape(self.shape))
            refinements += 1
        residual = float(np.linalg.norm(r) / b_norm) if b_norm else 0.0
        history.append(residual)
        u[...] = x.reshape(self.shape)
        return SolveInfo(refinements, residual, residual <= tol, history, time.perf_counter() - t0)

    def vcycle(self, b) -> np.ndarray:
        """One V-cycle from zero applied to ``b`` (the MGPCG preconditioner), for inspection."""
        return self._core.vcycle(self._cell_array(b, "b"))


def solve(f, h, bc="dirichlet", method="mgpcg", tol=1e-8, max_iter=None, x0=None, solid=None,
          **options):
    """Solves -lap(u) = f on the cell-centred grid of ``f.shape``. Returns ``(u, SolveInfo)``.

    f: (nx, ny[, nz]) right-hand side. h: cell size [m]. bc: "dirichlet", "neumann" or "periodic".
    method: one of :data:`METHODS`. tol: relative residual. max_iter: iteration cap.
    x0: initial guess. solid: optional bool mask of cells excluded from the domain.
    Further keywords go to :class:`Solver` (pre_smooth, post_smooth) and
    :meth:`Solver.solve` (rhs_mean, raise_on_failure).
    """
    f = grid_array(f, "f")
    solve_keys = {"rhs_mean", "raise_on_failure"}
    solver = Solver(f.shape, h, bc, method=method, solid=solid,
                    **{k: v for k, v in options.items() if k not in solve_keys})
    return solver.solve(f, tol=tol, max_iter=max_iter, x0=x0,
                        **{k: v for k, v in options.items() if k in solve_keys})


def laplacian(u, h, bc="dirichlet", solid=None) -> np.ndarray:
    """Applies the operator: returns A u = -lap(u) on the grid of ``u.shape`` (0 in solid cells)."""
    u = grid_array(u, "u")
    return Solver(u.shape, h, bc, method="cg", solid=solid).apply(u)


def matrix(shape, h, bc="dirichlet", solid=None) -> sp.csr_matrix:
    """The operator A = -lap as a scipy CSR matrix over all cells of ``shape`` (C order).

    Rows and columns of solid cells are empty; the matrix is symmetric, positive definite for
    Dirichlet problems and positive semi-definite (constants in its null space) for Neumann.
    """
    return Solver(shape, h, bc, method="cg", solid=solid).matrix()
