"""km.sparse: CHOLMOD Cholesky and CG against dense and scipy references.

Tolerances: a backward-stable solve has forward error ~ cond(A) * eps; bounds below are
C_FWD * cond * eps with cond computed from the eigenvalues (dense, small n) or analytically
(the Laplacian).
"""

import os
import signal
import threading
import time

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import kinema as km
from kinema.sparse import _csr_arrays

EPS = np.finfo(float).eps
C_FWD = 20.0  # safety factor on cond * eps (rounding grows slowly with n and fill)


def laplacian_1d(m):
    return sp.diags_array([-np.ones(m - 1), 2 * np.ones(m), -np.ones(m - 1)], offsets=[-1, 0, 1])


def laplacian_2d(m):
    """5-point -lap on an m x m grid (Dirichlet, h = 1), CSR with int64 indices."""
    t, eye = laplacian_1d(m), sp.eye_array(m)
    A = (sp.kron(t, eye) + sp.kron(eye, t)).tocsr()
    A.indptr = A.indptr.astype(np.int64)
    A.indices = A.indices.astype(np.int64)
    return A


def laplacian_2d_cond(m):
    theta = np.pi / (2 * (m + 1))
    return (np.sin(m * theta) / np.sin(theta)) ** 2


def random_spd(n, seed, density=0.02, shift=0.01):
    """B B^T + shift I with sparse random B: SPD, condition number ~3e3 for n = 300."""
    rng = np.random.default_rng(seed)
    B = sp.random_array((n, n), density=density, rng=rng, data_sampler=rng.standard_normal)
    return (B @ B.T + shift * sp.eye_array(n)).tocsr()


def cond(A):
    w = np.linalg.eigvalsh(A.toarray())
    return w[-1] / w[0]


def rel_err(x, ref):
    return np.linalg.norm(x - ref) / np.linalg.norm(ref)


# --------------------------------------------------------------------------- cholesky


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cholesky_matches_dense_and_spsolve(seed):
    A = random_spd(300, seed)
    rng = np.random.default_rng(100 + seed)
    b = rng.standard_normal(300)
    x = km.sparse.cholesky(A).solve(b)
    bound = C_FWD * cond(A) * EPS
    err_dense = rel_err(x, np.linalg.solve(A.toarray(), b))
    err_scipy = rel_err(x, spla.spsolve(A.tocsc(), b))
    assert err_dense <= bound, f"vs numpy.linalg.solve: {err_dense:.2e} > bound {bound:.2e}"
    assert err_scipy <= bound, f"vs scipy spsolve: {err_scipy:.2e} > bound {bound:.2e}"


def test_cholesky_laplacian_2d():
    m = 40
    A = laplacian_2d(m)
    b = np.random.default_rng(3).standard_normal(m * m)
    f = km.sparse.cholesky(A)
    x = f.solve(b)
    bound = C_FWD * laplacian_2d_cond(m) * EPS
    err = rel_err(x, spla.spsolve(A.tocsc(), b))
    assert err <= bound, f"vs spsolve: {err:.2e} > bound {bound:.2e}"
    assert f.n == m * m and f.is_supernodal and f.index_bits == 32
    assert f.nnz_factor >= (A.nnz + m * m) // 2  # L holds at least A's lower triangle
    assert sorted(f.permutation) == list(range(m * m))


def test_multiple_right_hand_sides():
    A = random_spd(200, 4)
    f = km.sparse.cholesky(A)
    B = np.random.default_rng(5).standard_normal((200, 7))
    X = f.solve(B)
    assert X.shape == (200, 7)
    bound = C_FWD * cond(A) * EPS
    for j in range(7):
        err = rel_err(X[:, j], f.solve(B[:, j]))
        assert err <= bound, f"column {j}: {err:.2e} > {bound:.2e}"
    err = rel_err(X, np.linalg.solve(A.toarray(), B))
    assert err <= bound, f"vs dense: {err:.2e} > {bound:.2e}"
    assert f.solve(np.empty((200, 0))).shape == (200, 0)
    # A non-contiguous b is accepted.
    assert np.array_equal(f.solve(np.asfortranarray(B)), X)


@pytest.mark.parametrize("fmt", ["coo", "csc", "lil", "dok", "bsr", "dia"])
def test_any_format_gives_the_same_answer(fmt):
    A = laplacian_2d(11) + sp.diags_array(np.linspace(0, 1, 121))  # few diagonals, for dia
    b = np.ones(121)
    ref = km.sparse.cholesky(A).solve(b)
    x = km.sparse.cholesky(sp.csr_matrix(A).asformat(fmt)).solve(b)
    assert np.array_equal(x, ref)


def test_unsorted_and_duplicate_entries():
    A = random_spd(80, 7).tocoo()
    # Split every value into two duplicates and shuffle the order: same matrix.
    rng = np.random.default_rng(8)
    row, col = np.r_[A.row, A.row], np.r_[A.col, A.col]
    order = np.lexsort((rng.random(row.size), row))  # grouped by row, shuffled within
    row, col = row[order], col[order]
    val = np.r_[0.25 * A.data, 0.75 * A.data][order]
    dup = sp.csr_matrix((val, (row, col)), shape=A.shape)  # scipy sums on conversion...
    raw = sp.csr_matrix((val, col, np.r_[0, np.cumsum(np.bincount(row, minlength=80))]),
                        shape=A.shape)  # ...this one keeps them, unsorted
    raw.has_sorted_indices = False
    b = np.arange(80.0)
    ref = np.linalg.solve(A.toarray(), b)
    bound = C_FWD * cond(A) * EPS
    for M in (dup, raw):
        err = rel_err(km.sparse.cholesky(M).solve(b), ref)
        assert err <= bound, f"{err:.2e} > {bound:.2e}"


def test_callers_matrix_is_not_modified():
    # An unsorted CSR is fixed on a copy, never in the caller's matrix.
    indptr = np.array([0, 2, 4])
    indices = np.array([1, 0, 1, 0])
    A = sp.csr_matrix((np.array([1.0, 4.0, 5.0, 1.0]), indices, indptr), shape=(2, 2))
    km.sparse.cholesky(A)
    assert list(A.indices) == [1, 0, 1, 0]


def test_no_copy_of_canonical_csr():
    A = laplacian_2d(8)
    _, indptr, indices, data = _csr_arrays(A, "A", True)
    assert np.shares_memory(data, A.data)
    assert np.shares_memory(indices, A.indices) and np.shares_memory(indptr, A.indptr)


def test_refactor_new_values_same_pattern():
    A = random_spd(150, 9)
    A2 = A.copy()
    A2.data *= 3.0
    A2.setdiag(A2.diagonal() + np.linspace(1, 2, 150))  # diagonal entries exist: same pattern
    assert np.array_equal(A2.indptr, A.indptr) and np.array_equal(A2.indices, A.indices)
    f = km.sparse.cholesky(A)
    perm = f.permutation
    f.refactor(A2)
    b = np.random.default_rng(10).standard_normal(150)
    bound = C_FWD * cond(A2) * EPS
    err = rel_err(f.solve(b), np.linalg.solve(A2.toarray(), b))
    assert err <= bound, f"after refactor: {err:.2e} > {bound:.2e}"
    assert np.array_equal(f.permutation, perm)  # the analysis was reused


def with_index_dtype(A, dtype):
    B = sp.csr_matrix(A, copy=True)
    B.sum_duplicates()  # canonical already: _csr_arrays then keeps the arrays as they are
    B.indptr = B.indptr.astype(dtype)
    B.indices = B.indices.astype(dtype)
    return B


def test_cholesky_reads_int32_and_int64_indices_alike():
    # scipy's int32 index arrays reach CHOLMOD without a 64-bit copy; the answer, the pattern
    # check of refactor and the symmetry check must not depend on the width.
    A = random_spd(120, 11)
    A32, A64 = with_index_dtype(A, np.int32), with_index_dtype(A, np.int64)
    assert _csr_arrays(A32, "A", True, keep_int32=True)[1].dtype == np.int32
    assert _csr_arrays(A64, "A", True, keep_int32=True)[1].dtype == np.int64
    b = np.random.default_rng(12).standard_normal(120)
    f32, f64 = km.sparse.cholesky(A32), km.sparse.cholesky(A64)
    assert np.array_equal(f32.solve(b), f64.solve(b))
    assert np.array_equal(f32.permutation, f64.permutation)
    f32.refactor(2 * A64)  # the other width, same pattern
    f64.refactor(with_index_dtype(2 * A, np.int32))
    assert np.array_equal(f32.solve(b), f64.solve(b))
    other = with_index_dtype(laplacian_2d(11)[:120, :120], np.int32)  # another pattern
    with pytest.raises(ValueError, match="A2: sparsity pattern differs"):
        f64.refactor(other)
    C = A32.tolil()
    C[0, 5] = C[0, 5] + 1.0
    with pytest.raises(ValueError, match=r"A: not symmetric: \|A\[0, 5\]"):
        km.sparse.cholesky(with_index_dtype(C.tocsr(), np.int32))


def test_refactor_rejects_another_pattern():
    A = laplacian_2d(10)
    f = km.sparse.cholesky(A)
    with pytest.raises(ValueError, match="^A2: sparsity pattern differs"):
        f.refactor(A + sp.eye_array(100, k=3) + sp.eye_array(100, k=-3))
    with pytest.raises(ValueError, match=r"^A2: expected shape \(100, 100\)"):
        f.refactor(laplacian_2d(11))
    x = f.solve(np.ones(100))  # the factor is still usable
    assert np.allclose(A @ x, 1.0)


def test_logdet():
    A = random_spd(100, 11)
    sign, ref = np.linalg.slogdet(A.toarray())
    assert sign == 1
    got = km.sparse.cholesky(A).logdet()
    assert abs(got - ref) <= 1e-10 * abs(ref), f"{got} vs {ref}"


def test_repr():
    r = repr(km.sparse.cholesky(laplacian_2d(5)))
    assert r.startswith("Factor(n=25, nnz_factor=") and "supernodal=True" in r


def test_shared_factor_in_threads():
    A = laplacian_2d(30)
    f = km.sparse.cholesky(A)
    rng = np.random.default_rng(12)
    bs = [rng.standard_normal(900) for _ in range(8)]
    ref = [f.solve(b) for b in bs]
    out = [None] * 8

    def work(i):
        out[i] = f.solve(bs[i])

    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.array_equal(o, r) for o, r in zip(out, ref))


# --------------------------------------------------------------------------- not SPD


def leading_minor_fails_at(k, n=30):
    """Tridiagonal -1, 2, -1 whose first k leading minors are positive and (k+1)-th negative.

    The Cholesky pivots of the Laplacian are d_j = (j + 2) / (j + 1); setting
    a_kk = 1 / d_{k-1} - 1/2 makes pivot k equal to -1/2.
    """
    A = laplacian_1d(n).tolil()
    A[k, k] = (k / (k + 1)) - 0.5 if k > 0 else -0.5
    return A.tocsr()


@pytest.mark.parametrize("k", [0, 1, 7, 29])
def test_not_positive_definite_leading_minor(k):
    A = leading_minor_fails_at(k)
    minors = [np.linalg.det(A.toarray()[: j + 1, : j + 1]) for j in range(k + 1)]
    assert all(m > 0 for m in minors[:k]) and minors[k] < 0  # the test matrix is as claimed
    with pytest.raises(km.NotPositiveDefiniteError, match="not positive definite") as e:
        km.sparse.cholesky(A, ordering="natural")
    assert e.value.column == k, f"column {e.value.column}, expected {k}"
    assert isinstance(e.value, ValueError)


@pytest.mark.parametrize("k", [0, 57, 199])
def test_not_positive_definite_any_ordering(k):
    # A very negative a_kk fails at column k whatever the elimination order: pivots before k
    # do not see it, and k's own pivot is a_kk minus a non-negative sum.
    A = random_spd(200, 13).tolil()
    A[k, k] = -10.0 * (1 + abs(A[k, k]) + float(np.abs(A[[k], :].toarray()).sum()))
    for ordering in ("default", "amd", "metis"):
        with pytest.raises(km.NotPositiveDefiniteError) as e:
            km.sparse.cholesky(A, ordering=ordering)
        assert e.value.column == k, f"{ordering}: column {e.value.column}, expected {k}"


def test_refactor_not_positive_definite_then_recover():
    A = laplacian_1d(30).tocsr()
    f = km.sparse.cholesky(A, ordering="natural")
    bad = leading_minor_fails_at(12)
    with pytest.raises(km.NotPositiveDefiniteError, match="^A2:") as e:
        f.refactor(bad)
    assert e.value.column == 12
    with pytest.raises(km.KinemaError, match="last factorisation failed"):
        f.solve(np.ones(30))
    f.refactor(A)
    x = f.solve(np.ones(30))
    assert np.allclose(A @ x, 1.0, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- cg


def test_cg_converges_to_tol_with_true_residual():
    m = 64
    A = laplacian_2d(m)
    b = np.random.default_rng(14).standard_normal(m * m)
    for tol in (1e-6, 1e-10):
        x, info = km.sparse.cg(A, b, tol=tol)
        true = np.linalg.norm(b - A @ x) / np.linalg.norm(b)
        assert info.converged and info.residual <= tol * 1.01, info
        assert abs(true - info.residual) <= 1e-3 * info.residual + 1e-15, (true, info.residual)
        assert len(info.history) == info.iterations + 1 and info.history[0] == 1.0
        assert info.seconds > 0
        # Forward error: ||x - x*|| / ||x*|| <= cond * relative residual.
        bound = laplacian_2d_cond(m) * true + C_FWD * laplacian_2d_cond(m) * EPS
        err = rel_err(x, km.sparse.cholesky(A).solve(b))
        assert err <= bound, f"tol {tol}: error {err:.2e} > {bound:.2e}"


def test_cg_initial_guess():
    A = laplacian_2d(20)
    b = np.ones(400)
    exact = km.sparse.cholesky(A).solve(b)
    x0 = exact.copy()
    x, info = km.sparse.cg(A, b, x0=x0, tol=1e-8)
    assert info.iterations == 0 and info.converged
    assert np.array_equal(x0, exact)  # x0 is not modified
    x, info = km.sparse.cg(A, np.zeros(400))
    assert info.converged and not x.any()


def test_jacobi_reduces_iterations_on_badly_scaled_matrix():
    # D L D with D spanning three decades: cond grows by ~10^6, Jacobi undoes the scaling.
    m = 24
    d = np.logspace(0, 3, m * m)
    d = np.random.default_rng(15).permutation(d)
    A = (sp.diags_array(d) @ laplacian_2d(m) @ sp.diags_array(d)).tocsr()
    b = A @ np.ones(m * m)
    _, plain = km.sparse.cg(A, b, precond=None, tol=1e-8, max_iter=5000, raise_on_failure=False)
    x, jac = km.sparse.cg(A, b, precond="jacobi", tol=1e-8)
    assert jac.converged
    assert jac.iterations * 3 <= plain.iterations, (jac.iterations, plain.iterations)
    assert np.linalg.norm(b - A @ x) / np.linalg.norm(b) <= 1.01e-8


def test_cg_convergence_error():
    A = laplacian_2d(32)
    b = np.ones(1024)
    with pytest.raises(km.ConvergenceError, match="no convergence in 3 iterations") as e:
        km.sparse.cg(A, b, max_iter=3)
    info = e.value.info
    assert isinstance(info, km.SolveInfo)
    assert info.iterations == 3 and not info.converged and info.residual > 1e-8
    x, info = km.sparse.cg(A, b, max_iter=3, raise_on_failure=False)
    assert info.iterations == 3 and not info.converged
    assert np.isclose(np.linalg.norm(b - A @ x) / np.linalg.norm(b), info.residual)


def test_cg_not_positive_definite():
    A = sp.diags_array(np.r_[-1.0, np.ones(9)]).tocsr()
    b = np.r_[1.0, np.zeros(9)]  # the first direction is e_0: p^T A p = -1
    with pytest.raises(ValueError, match="^A: not positive definite"):
        km.sparse.cg(A, b, precond=None)


# --------------------------------------------------------------------------- determinism


def test_determinism_and_thread_independence():
    m = 128  # n = 16384: above the parallel grain, so both threads work
    A = laplacian_2d(m)
    b = np.random.default_rng(16).standard_normal(m * m)
    saved = km.get_num_threads()
    try:
        runs = []
        for threads in (2, 2, 1):
            km.set_num_threads(threads)
            runs.append(km.sparse.cg(A, b, tol=1e-9))
    finally:
        km.set_num_threads(saved)
    (x0, i0) = runs[0]
    for x, info in runs[1:]:
        assert np.array_equal(x, x0) and info.history == i0.history
    f = km.sparse.cholesky(A)
    assert np.array_equal(f.solve(b), f.solve(b))
    assert np.array_equal(km.sparse.cholesky(A).solve(b), f.solve(b))


# --------------------------------------------------------------------------- Ctrl-C


def test_cg_is_interruptible():
    A = laplacian_2d(512)  # unpreconditioned CG needs thousands of iterations: many seconds
    b = np.ones(A.shape[0])
    fired = []

    def interrupt():
        fired.append(time.perf_counter())
        os.kill(os.getpid(), signal.SIGINT)

    # A shell without job control starts background jobs with SIGINT ignored, and Python then
    # keeps it ignored: install Python's own handler, as an interactive session has it.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(0.3, interrupt)
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            km.sparse.cg(A, b, tol=1e-14, max_iter=20000, precond=None, check_symmetry=False)
        caught = time.perf_counter()
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert fired, "cg returned before the interrupt was sent"
    delay = caught - fired[0]
    assert delay < 1.0, f"KeyboardInterrupt {delay:.2f} s after SIGINT (bound 1 s)"


# --------------------------------------------------------------------------- OpenBLAS


def test_supernodal_on_openblas():
    info = km.build_info()
    assert "openblas" in info["blas"].lower() or info["blas_config"].startswith("OpenBLAS"), info
    m = 256
    A = laplacian_2d(m)
    f = km.sparse.cholesky(A)
    assert f.is_supernodal
    b = np.random.default_rng(17).standard_normal(m * m)
    x = f.solve(b)
    res = np.linalg.norm(b - A @ x) / np.linalg.norm(b)
    assert res <= 1e3 * EPS, f"relative residual {res:.2e} > {1e3 * EPS:.2e}"


# --------------------------------------------------------------------------- bad input


GOOD = laplacian_2d(4)  # n = 16


def _nan_matrix():
    A = GOOD.copy()
    A.data[3] = np.nan
    return A


def _nonsymmetric(i, j, value):
    A = GOOD.tolil()
    A[i, j] = value
    return A.tocsr()


@pytest.mark.parametrize(
    "A, match",
    [
        ([[2.0, 0.0], [0.0, 2.0]], "A: expected a scipy.sparse matrix"),
        (np.eye(3), "A: expected a scipy.sparse matrix"),
        (None, "A: expected a scipy.sparse matrix"),
        (sp.csr_array((3, 4)), r"A: expected a square matrix, got shape \(3, 4\)"),
        (sp.csr_array((0, 0)), "A: expected a non-empty matrix"),
        (sp.eye_array(3, dtype=complex), "A: expected real values"),
        (_nan_matrix(), "A: non-finite value nan"),
        (sp.coo_array(np.ones(3)), r"A: expected a square matrix, got shape \(3,\)"),
        (_nonsymmetric(0, 1, -0.5), r"A: not symmetric: \|A\[0, 1\] - A\[1, 0\]\| = 5.000e-01"),
        (_nonsymmetric(0, 5, 1.0), r"A: not symmetric: \|A\[0, 5\] - A\[5, 0\]\| = 1.000e\+00"),
    ],
)
def test_bad_matrix(A, match):
    with pytest.raises(ValueError, match=match):
        km.sparse.cholesky(A)
    with pytest.raises(ValueError, match=match):
        km.sparse.cg(A, np.ones(16))


def test_rounding_asymmetry_is_accepted():
    A = GOOD.copy()
    A.data = A.data.copy()
    A.data[1] *= 1 + 1e-14  # a_01 = -1 (1 + 1e-14), a_10 = -1
    km.sparse.cholesky(A)
    with pytest.raises(ValueError, match="not symmetric"):
        km.sparse.cholesky(_nonsymmetric(0, 1, -1 - 1e-8))


def test_upper_triangle_alone_without_symmetry_check():
    A = random_spd(100, 18)
    b = np.ones(100)
    ref = km.sparse.cholesky(A).solve(b)
    x = km.sparse.cholesky(sp.triu(A, format="csr"), check_symmetry=False).solve(b)
    assert np.array_equal(x, ref)


def test_bad_solve_arguments():
    f = km.sparse.cholesky(GOOD)
    for b, match in [
        (np.ones(15), r"b: expected shape \(16,\) or \(16, k\), got \(15,\)"),
        (np.ones((16, 2, 2)), "b: expected a 1 or 2-dimensional array"),
        (np.r_[np.ones(15), np.inf], "b: contains 1 non-finite"),
        ("abc", "b: expected an array of real numbers"),
    ]:
        with pytest.raises(ValueError, match=match):
            f.solve(b)


def test_bad_cg_arguments():
    b = np.ones(16)
    cases = [
        (dict(b=np.ones(17)), r"b: expected shape \(16,\), got \(17,\)"),
        (dict(b=np.ones((16, 1))), r"b: expected shape \(16,\)"),
        (dict(b=np.r_[np.ones(15), np.nan]), "b: contains 1 non-finite"),
        (dict(x0=np.ones(3)), r"x0: expected shape \(16,\)"),
        (dict(tol=0.0), "tol: expected a finite number > 0"),
        (dict(tol=float("nan")), "tol:"),
        (dict(max_iter=0), "max_iter: expected an integer >= 1"),
        (dict(max_iter=2.5), "max_iter:"),
        (dict(precond="ilu"), "precond: expected None or 'jacobi'"),
        (dict(precond=np.ones(2)), "precond: expected None or 'jacobi'"),
    ]
    for kwargs, match in cases:
        args = dict(b=b) | kwargs
        with pytest.raises(ValueError, match=match):
            km.sparse.cg(GOOD, **args)
    for ordering in ("nesdis", None, ["amd"]):
        with pytest.raises(ValueError, match="ordering: expected one of"):
            km.sparse.cholesky(GOOD, ordering=ordering)


@pytest.mark.parametrize("diagonal", [0.0, -1.0])
def test_jacobi_needs_positive_diagonal(diagonal):
    A = GOOD.tolil()
    A[3, 3] = diagonal
    with pytest.raises(ValueError, match=r"A: diagonal entry A\[3, 3\] = .* is not positive"):
        km.sparse.cg(A.tocsr(), np.ones(16))


def test_zero_matrix_is_not_positive_definite():
    A = sp.csr_array((np.zeros(3), np.arange(3), np.arange(4)), shape=(3, 3))
    with pytest.raises(km.NotPositiveDefiniteError) as e:
        km.sparse.cholesky(A)
    assert e.value.column == 0


def test_metis_ordering_solves_with_less_fill():
    # Nested dissection fills in less than AMD on a 2D grid Laplacian; both solve it exactly.
    A = km.poisson.matrix((128, 128), 1.0)  # at 64^2 AMD still wins; from ~128^2 on METIS does
    b = np.random.default_rng(12).standard_normal(A.shape[0])
    amd, metis = km.sparse.cholesky(A, ordering="amd"), km.sparse.cholesky(A, ordering="metis")
    for f in (amd, metis):
        r = np.linalg.norm(b - A @ f.solve(b)) / np.linalg.norm(b)
        assert r < 1e-13, (f.ordering, r)
    assert metis.nnz_factor < amd.nnz_factor, (metis.nnz_factor, amd.nnz_factor)
