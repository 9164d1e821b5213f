"""km.sparse: symmetric positive definite sparse systems A x = b.

- :func:`cholesky` factorises A once with CHOLMOD's supernodal Cholesky P A P^T = L L^T
  (Chen, Davis, Hager & Rajamanickam, ACM TOMS 35, 2008); the :class:`Factor` then solves for
  any number of right-hand sides and re-factorises new values of the same pattern cheaply.
- :func:`cg` solves by conjugate gradients (Hestenes & Stiefel 1952), Jacobi-preconditioned
  by default.

Matrices: any scipy.sparse format (``*_matrix`` or ``*_array``), square, real, finite and
symmetric (checked against the transpose, relative tolerance ``SYMMETRY_RTOL`` of max |a_ij|).
They are passed to C++ as CSR with int64 indices and float64 values; a canonical CSR float64
matrix is used without copying its values (int32 index arrays are widened, a copy). Dense
arrays are refused rather than silently converted: wrap them with ``scipy.sparse.csr_array``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from kinema import _core
from kinema._checks import as_float_array, positive, positive_int, representable
from kinema._info import SolveInfo
from kinema.errors import ConvergenceError, DivergenceError

__all__ = ["Factor", "cholesky", "cg", "SYMMETRY_RTOL"]

# |a_ij - a_ji| allowed relative to max |a_ij|: far above assembly rounding (~1e-15), far below
# any modelling asymmetry.
SYMMETRY_RTOL = 1e-10

_ORDERINGS = ("default", "amd", "metis", "natural")


def _csr_arrays(A, name, check_symmetry, keep_int32=False):
    """(n, indptr, indices, data) of ``A`` as canonical CSR, int64/int64/float64, checked; with
    keep_int32, scipy's int32 index arrays are passed on as they are (no 64-bit copy)."""
    if not sp.issparse(A):
        raise ValueError(
            f"{name}: expected a scipy.sparse matrix (any format), got {type(A).__name__}; "
            "wrap a dense array with scipy.sparse.csr_array(...)")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"{name}: expected a square matrix, got shape {A.shape}")
    n = A.shape[0]
    if n == 0:
        raise ValueError(f"{name}: expected a non-empty matrix, got shape {A.shape}")
    if A.dtype.kind not in "biuf":
        raise ValueError(f"{name}: expected real values, got dtype {A.dtype}")
    if A.format != "csr":
        A = A.tocsr()  # sums duplicates, sorts indices
    if not A.has_canonical_format:
        A = A.copy()  # never reorder the caller's matrix in place
        A.sum_duplicates()
    index_dtype = np.int32 if keep_int32 and A.indptr.dtype == A.indices.dtype == np.int32 else np.int64
    indptr = np.ascontiguousarray(A.indptr, dtype=index_dtype)
    indices = np.ascontiguousarray(A.indices, dtype=index_dtype)
    data = np.ascontiguousarray(A.data, dtype=np.float64)
    if not np.isfinite(data).all():
        p = int(np.flatnonzero(~np.isfinite(data))[0])
        i = int(np.searchsorted(indptr, p, side="right") - 1)
        raise ValueError(f"{name}: non-finite value {data[p]} at ({i}, {indices[p]}) "
                         f"({np.count_nonzero(~np.isfinite(data))} in all)")
    if check_symmetry:
        _check_symmetric(n, indptr, indices, data, name)
    return n, indptr, indices, data


def _check_symmetric(n, indptr, indices, data, name):
    """Raises unless |a_ij - a_ji| <= SYMMETRY_RTOL * max |a_ij| (canonical CSR arrays)."""
    bound = SYMMETRY_RTOL * float(np.abs(data).max(initial=0.0))
    diff, i, j = _core.sparse.asymmetry(n, indptr, indices, data)
    if diff > bound:
        raise ValueError(
            f"{name}: not symmetric: |A[{i}, {j}] - A[{j}, {i}]| = {diff:.3e} exceeds "
            f"{bound:.3e} (SYMMETRY_RTOL * max |a_ij|); symmetrise with (A + A.T) / 2 if the "
            "difference is rounding (check_symmetry=False skips this check)")


def _vector(x, name, n):
    a = as_float_array(x, name)
    if a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    return a


def _renamed(exc, name):
    """``exc`` with its leading "A:" replaced by "<name>:", same class and attributes."""
    message = str(exc)
    if not message.startswith("A:"):
        return exc
    new = type(exc)(name + message[1:])
    new.__dict__.update(exc.__dict__)
    return new


class Factor:
    """Cholesky factorisation P A P^T = L L^T of a sparse SPD matrix, from :func:`cholesky`.

    n: size of A (A is n x n).
    nnz_factor: nonzeros in L, as counted by CHOLMOD's analysis.
    is_supernodal: True (the factorisation is always supernodal: dense BLAS-3 blocks).
    index_bits: 32 when CHOLMOD's int interface is used (whenever A and L fit in it: less
        index traffic), 64 for its long interface (cholmod_l_*) otherwise.
    ordering: the fill-reducing ordering requested ("default", "amd" or "natural").
    permutation: (n,) int64, P as an index array: row/column permutation[k] of A is row/column
        k of P A P^T (a copy).

    A factor may be shared between threads; its calls run one at a time.
    """

    __slots__ = ("_core", "_ordering")

    def __init__(self, core, ordering):
        self._core = core
        self._ordering = ordering

    @property
    def ordering(self) -> str:
        return self._ordering

    @property
    def n(self) -> int:
        return self._core.n

    @property
    def nnz_factor(self) -> int:
        return self._core.nnz_factor

    @property
    def is_supernodal(self) -> bool:
        return self._core.is_supernodal

    @property
    def index_bits(self) -> int:
        return self._core.index_bits

    @property
    def permutation(self) -> np.ndarray:
        return self._core.permutation

    def solve(self, b) -> np.ndarray:
        """x = A^-1 b.

        b: (n,) or (n, k) for k right-hand sides, in the units of A x.
        Returns x of b's shape, in the units of b / A (for (n, k), a Fortran-ordered array).
        """
        n = self.n
        b = as_float_array(b, "b", ndim=(1, 2))
        if b.shape[0] != n:
            raise ValueError(f"b: expected shape ({n},) or ({n}, k), got {b.shape}")
        if b.ndim == 1:
            return representable(self._core.solve(b), "b", "A^-1 b")
        # CHOLMOD takes right-hand sides column-major: the (k, n) C-ordered transpose.
        return representable(self._core.solve(np.ascontiguousarray(b.T)).T, "b", "A^-1 b")

    def refactor(self, A2, *, check_symmetry: bool = True) -> None:
        """Re-factorises new values with the same sparsity pattern, reusing the analysis.

        A2: scipy.sparse (n, n) SPD matrix whose stored pattern (after summing duplicates)
            equals the factorised one's; raises ValueError otherwise, and
            km.NotPositiveDefiniteError (the factor is then unusable until a successful
            refactor) when a pivot fails.
        """
        n, indptr, indices, data = _csr_arrays(A2, "A2", check_symmetry, keep_int32=True)
        if n != self.n:
            raise ValueError(f"A2: expected shape ({self.n}, {self.n}), got {A2.shape}")
        try:
            self._core.refactor(n, indptr, indices, data)
        except ValueError as exc:
            raise _renamed(exc, "A2") from None

    def logdet(self) -> float:
        """log det A = 2 sum_j log L_jj (no overflow, unlike det)."""
        return self._core.logdet()

    def __repr__(self) -> str:
        return (f"Factor(n={self.n}, nnz_factor={self.nnz_factor}, "
                f"supernodal={self.is_supernodal}, ordering={self.ordering!r})")


def cholesky(A, *, ordering: str = "default", check_symmetry: bool = True) -> Factor:
    """Factorises a sparse symmetric positive definite matrix with CHOLMOD (supernodal).

    A: scipy.sparse (n, n), symmetric positive definite, any format. Only the upper triangle
        (j >= i) is read; the lower one is checked for symmetry. With ``check_symmetry=False``
        the check is skipped, and ``scipy.sparse.triu(A)`` alone may be passed.
    ordering: fill-reducing ordering, "default" (CHOLMOD's choice: AMD, or METIS when AMD
        fills in poorly), "amd", or "natural" (none; the failing column of a non-SPD matrix is
        then the first non-positive leading minor).

    Raises km.NotPositiveDefiniteError (``.column``: the zero-based column of A whose pivot
    failed) when A is not positive definite, ValueError for any malformed input.
    """
    if not isinstance(ordering, str) or ordering not in _ORDERINGS:
        raise ValueError(f"ordering: expected one of {_ORDERINGS}, got {ordering!r}")
    n, indptr, indices, data = _csr_arrays(A, "A", check_symmetry, keep_int32=True)
    return Factor(_core.sparse.Factor(n, indptr, indices, data, ordering), ordering)


def cg(A, b, x0=None, tol=1e-8, max_iter=None, precond="jacobi", *,
       raise_on_failure: bool = True, check_symmetry: bool = True):
    """Solves A x = b by (preconditioned) conjugate gradients.

    A: scipy.sparse (n, n) symmetric positive definite, any format, checked for symmetry
        unless ``check_symmetry=False`` (CG needs a symmetric A).
    b: (n,) right-hand side, in the units of A x.
    x0: (n,) initial guess (default zeros; not modified), in the units of x.
    tol: stop when the relative residual ||b - A x|| / ||b|| <= tol.
    max_iter: iteration limit (default max(2 n, 100)).
    precond: None or "jacobi" (M = diag(A); needs a positive diagonal).
    raise_on_failure: when max_iter is reached before tol, raise km.ConvergenceError (its
        ``.info`` holds the SolveInfo) if True, else return with ``info.converged = False``.

    Returns (x, info): x (n,) in the units of b / A, info a km.SolveInfo whose ``residual`` is the true relative
    residual of x. Interruptible with Ctrl-C (KeyboardInterrupt).
    """
    n, indptr, indices, data = _csr_arrays(A, "A", check_symmetry)
    b = _vector(b, "b", n)
    x = np.zeros(n) if x0 is None else np.array(_vector(x0, "x0", n), copy=True)
    tol = positive(tol, "tol")
    max_iter = positive_int(max_iter, "max_iter", allow_none=True) or 0
    if precond is not None and not (isinstance(precond, str) and precond == "jacobi"):
        raise ValueError(f"precond: expected None or 'jacobi', got {precond!r}")
    try:
        info: SolveInfo = _core.sparse.cg(n, indptr, indices, data, b, x, precond == "jacobi", tol,
                                          max_iter)
    except DivergenceError as exc:
        # A, b and x0 are finite: the iterates overflowed, or A is not positive definite
        raise ValueError(f"A, b: {exc} (A not positive definite, or values that overflow float64: "
                         "scale A or b into a smaller range)") from None
    if not info.converged and raise_on_failure:
        err = ConvergenceError(
            f"cg: no convergence in {info.iterations} iterations: relative residual "
            f"{info.residual:.3e} > tol = {tol:.1e}; raise max_iter"
            + (", precondition (precond='jacobi')" if precond is None else "")
            + " or solve directly with km.sparse.cholesky")
        err.info = info
        raise err
    return x, info
