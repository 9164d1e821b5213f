"""km.fmm: the fast multipole method against the direct sum for several eps, sizes and point
distributions (phi and gradient), invariance under translation and scaling, degenerate input
(duplicates, a single point, empty sets), determinism, and the handling of bad input."""

import time

import numpy as np
import pytest

import kinema as km

EPS = [1e-3, 1e-6, 1e-10, 1e-13]


def distribution(name, n, seed=0):
    rng = np.random.default_rng(seed)
    if name == "uniform":
        return rng.random((n, 2))
    if name == "clustered":
        # radii spread over ~12 decades around the origin, plus a far cloud
        r = 10.0 ** rng.uniform(-12, 0, n)
        a = rng.uniform(0, 2 * np.pi, n)
        pts = np.c_[r * np.cos(a), r * np.sin(a)]
        pts[: n // 10] += 5.0
        return pts
    if name == "curve":
        t = rng.uniform(0, 2 * np.pi, n)
        return np.c_[np.cos(t), 0.3 * np.sin(3 * t)]
    if name == "duplicates":
        base = rng.random((n // 4, 2))
        return base[rng.integers(0, n // 4, n)]
    raise ValueError(name)


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def check(phi, grad, phi_ref, grad_ref, eps, where):
    e_phi, e_grad = rel(phi, phi_ref), rel(grad, grad_ref)
    assert e_phi < eps, f"{where}: phi relative error {e_phi:.3e} above eps {eps:g}"
    assert e_grad < eps, f"{where}: gradient relative error {e_grad:.3e} above eps {eps:g}"


@pytest.mark.parametrize("eps", EPS)
@pytest.mark.parametrize("dist", ["uniform", "clustered", "curve", "duplicates"])
def test_self_interaction_matches_direct(dist, eps):
    x = distribution(dist, 4000)
    q = np.random.default_rng(1).uniform(-1, 1, len(x))
    phi, grad = km.fmm.laplace2d(x, q, eps=eps, gradient=True)
    phi_ref, grad_ref = km.fmm.direct2d(x, q, gradient=True)
    assert np.isfinite(phi).all() and np.isfinite(grad).all()
    check(phi, grad, phi_ref, grad_ref, eps, f"{dist}, targets = sources")


@pytest.mark.parametrize("eps", EPS)
@pytest.mark.parametrize("dist", ["uniform", "clustered", "curve"])
def test_separate_targets_match_direct(dist, eps):
    x = distribution(dist, 3000, seed=2)
    y = distribution(dist, 2000, seed=3) * 1.5 + 0.1
    q = np.random.default_rng(4).uniform(0, 1, len(x))  # all positive: no cancellation
    phi, grad = km.fmm.laplace2d(x, q, y, eps=eps, gradient=True)
    phi_ref, grad_ref = km.fmm.direct2d(x, q, y, gradient=True)
    check(phi, grad, phi_ref, grad_ref, eps, f"{dist}, separate targets")


def test_targets_equal_to_sources_leave_the_self_term_out():
    x = distribution("uniform", 2000)
    q = np.random.default_rng(5).normal(size=len(x))
    a = km.fmm.laplace2d(x, q, eps=1e-10)
    b = km.fmm.laplace2d(x, q, x.copy(), eps=1e-10)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * np.abs(a).max())


def test_large_n_against_direct_on_a_subset():
    x = distribution("uniform", 200_000, seed=6)
    q = np.random.default_rng(7).uniform(-1, 1, len(x))
    for eps in (1e-4, 1e-12):
        phi, grad = km.fmm.laplace2d(x, q, eps=eps, gradient=True)
        idx = np.random.default_rng(8).choice(len(x), 300, replace=False)
        phi_ref, grad_ref = km.fmm.direct2d(x, q, x[idx], gradient=True)
        check(phi[idx], grad[idx], phi_ref, grad_ref, eps, f"N = 2e5, eps = {eps:g}, 300 targets")


@pytest.mark.parametrize("shift, scale", [(100.0, 1.0), (0.0, 1e-6), (0.0, 1e6), (-30.0, 1e3)])
def test_translation_and_scaling(shift, scale):
    # phi(s x + t) = phi(x) + Q log s: the FMM must stay within eps on the transformed input.
    eps = 1e-9
    x = distribution("uniform", 3000, seed=9) * scale + shift
    q = np.random.default_rng(10).uniform(-1, 1, len(x))
    phi, grad = km.fmm.laplace2d(x, q, eps=eps, gradient=True)
    phi_ref, grad_ref = km.fmm.direct2d(x, q, gradient=True)
    check(phi, grad, phi_ref, grad_ref, eps, f"shift {shift}, scale {scale}")


def test_analytic_two_charges():
    x = np.array([[0.0, 0.0], [3.0, 4.0]])
    q = np.array([2.0, -1.0])
    y = np.array([[3.0, 0.0]])
    phi, grad = km.fmm.laplace2d(x, q, y, gradient=True)
    assert phi[0] == pytest.approx(2 * np.log(3) - np.log(4), rel=1e-14)
    np.testing.assert_allclose(grad[0], [2 / 3, 1 / 4], rtol=1e-14)


def test_degenerate_inputs():
    # one point: no other charge, so zero; coincident points: pairs at distance 0 left out
    np.testing.assert_array_equal(km.fmm.laplace2d([[0.5, 0.5]], [1.0]), [0.0])
    same = np.ones((500, 2))
    phi, grad = km.fmm.laplace2d(same, np.ones(500), gradient=True)
    assert np.all(phi == 0) and np.all(grad == 0)
    phi = km.fmm.laplace2d(same, np.ones(500), [[1.0, 2.0]])
    assert phi[0] == pytest.approx(0.0, abs=1e-12)
    assert km.fmm.laplace2d(np.zeros((0, 2)), np.zeros(0), [[1.0, 1.0]])[0] == 0
    assert km.fmm.laplace2d(np.ones((3, 2)), np.ones(3), np.zeros((0, 2))).shape == (0,)
    phi, grad = km.fmm.laplace2d(np.zeros((0, 2)), np.zeros(0), gradient=True)
    assert phi.shape == (0,) and grad.shape == (0, 2)


def test_bitwise_identical_across_threads():
    x = distribution("clustered", 20_000, seed=11)
    q = np.random.default_rng(12).uniform(-1, 1, len(x))
    saved = km.get_num_threads()
    try:
        results = []
        for t in (1, 2, 1):
            km.set_num_threads(t)
            results.append(km.fmm.laplace2d(x, q, eps=1e-8, gradient=True))
    finally:
        km.set_num_threads(saved)
    for phi, grad in results[1:]:
        np.testing.assert_array_equal(phi, results[0][0])
        np.testing.assert_array_equal(grad, results[0][1])


def test_clustered_points_keep_the_tree_adaptive():
    # 1e5 points at one place (1e-13 apart) beside a uniform cloud: the tree goes deep there
    # instead of degrading to a quadratic direct sum.
    rng = np.random.default_rng(13)
    x = np.r_[rng.random((50_000, 2)), 0.5 + 1e-13 * rng.random((50_000, 2))]
    q = rng.uniform(-1, 1, len(x))
    phi = km.fmm.laplace2d(x, q, eps=1e-6)
    info = km.fmm.last_info()
    assert info["depth"] > 30, info
    idx = rng.choice(len(x), 200, replace=False)
    assert rel(phi[idx], km.fmm.direct2d(x, q, x[idx])) < 1e-6


@pytest.mark.parametrize("kwargs, match", [
    (dict(sources=np.zeros((3, 3)), charges=np.zeros(3)), "sources"),
    (dict(sources=np.zeros(6), charges=np.zeros(3)), "sources"),
    (dict(sources=np.zeros((3, 2)), charges=np.zeros(4)), "charges"),
    (dict(sources=np.zeros((3, 2)), charges=np.zeros((3, 1))), "charges"),
    (dict(sources=np.zeros((3, 2)), charges=np.ones(3) * 1j), "charges"),
    (dict(sources=[[0, 0], [np.nan, 1]], charges=[1, 1]), "sources"),
    (dict(sources=[[0, 0], [1, 1]], charges=[1, np.inf]), "charges"),
    (dict(sources=[[0, 0]], charges=[1], targets=[[0, 1, 2]]), "targets"),
    (dict(sources=[[0, 0]], charges=[1], targets=[[0, np.nan]]), "targets"),
    (dict(sources=[[0, 0]], charges=[1], eps=0.0), "eps"),
    (dict(sources=[[0, 0]], charges=[1], eps=1e-16), "eps"),
    (dict(sources=[[0, 0]], charges=[1], eps=2.0), "eps"),
    (dict(sources=[[0, 0]], charges=[1], eps="tight"), "eps"),
    (dict(sources=[[0, 0]], charges=[1], order=0), "order"),
    (dict(sources=[[0, 0]], charges=[1], order=500), "order"),
    (dict(sources=[[0, 0]], charges=[1], leaf_size=-1), "leaf_size"),
    (dict(sources="abc", charges=[1]), "sources"),
])
def test_bad_input_raises_value_error_naming_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        km.fmm.laplace2d(**kwargs)


def test_direct2d_bad_input():
    with pytest.raises(ValueError, match="sources"):
        km.fmm.direct2d(np.zeros((2, 3)), np.zeros(2))
    with pytest.raises(ValueError, match="charges"):
        km.fmm.direct2d(np.zeros((2, 2)), np.zeros(3))


@pytest.mark.slow
@pytest.mark.parametrize("eps", [1e-3, 1e-8, 1e-13])
@pytest.mark.parametrize("dist", ["uniform", "clustered", "curve"])
def test_one_million_points_subset(dist, eps):
    x = distribution(dist, 1_000_000, seed=14)
    q = np.random.default_rng(15).uniform(-1, 1, len(x))
    phi, grad = km.fmm.laplace2d(x, q, eps=eps, gradient=True)
    idx = np.random.default_rng(16).choice(len(x), 500, replace=False)
    phi_ref, grad_ref = km.fmm.direct2d(x, q, x[idx], gradient=True)
    check(phi[idx], grad[idx], phi_ref, grad_ref, eps, f"{dist}, N = 1e6, 500 targets")


@pytest.mark.parametrize("which", ["direct2d", "laplace2d"])
def test_ctrl_c_interrupts_a_long_sum(which, ctrl_c_delay):
    rng = np.random.default_rng(17)
    if which == "direct2d":
        x = rng.random((200_000, 2))  # 4e10 pairs: minutes
        run = lambda: km.fmm.direct2d(x, np.ones(len(x)))
    else:
        x = 0.5 + 1e-12 * rng.random((3_000_000, 2))  # a deep tree: several seconds
        run = lambda: km.fmm.laplace2d(x, np.ones(len(x)), eps=1e-13)
    # CPU seconds, not wall: other processes' load stretches the wall time of the same work
    # (2.5 s against a 2 s wall bound was seen under load). The laplace2d call costs ~11 CPU s
    # and direct2d minutes. Measured CPU seconds from the signal to the exception: direct2d
    # 0.01-0.08, laplace2d 0.05-0.21 with the signal 0.5-6 s into the call and 0.70 at 8 s (its
    # longest stretch between checks, late in the call); the poll runs every 0.1 s of wall time
    # (<= 0.2 CPU s on two threads): bound 1.5 CPU s, a seventh of what a call that ignored
    # Ctrl-C would spend.
    cpu = ctrl_c_delay(run, clock=time.process_time)
    assert cpu < 1.5, f"{which} spent {cpu:.2f} CPU s after Ctrl-C"
