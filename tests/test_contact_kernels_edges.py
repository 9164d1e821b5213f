"""The edge-edge barrier term m(s) b(d) with IPC's mollifier (Li et al. 2020, sec. 4.1) on
exactly parallel, parallel-to-rounding and nearly parallel edges: its gradient against central
differences of its energy and its Hessian against central differences of its gradient.

Why orders and not one tolerance: the segment distance d has a kink where two overlapping edges
turn parallel (the closest points jump from one end to the other), and the mollifier
m(s) = (2 - s / eps_x) s / eps_x on s = |(a1 - a0) x (b1 - b0)|^2 cancels it: along any line
x0 + t u through a parallel configuration s = O(t^2), so m b is C^2 in t with a bounded (one-sided)
third derivative. Central differences of the energy then err by O(eps^2), and of the gradient by
O(eps) at an exactly parallel pair (the second derivative of the gradient may jump there) and by
O(eps^2) off it. Each test measures the error at eps, eps/2, eps/4, eps/8 and asserts the fitted
log-log slope within 0.2 of that order; the unmollified term fails the same check (its gradient
jumps), which the last test asserts so the check is known to bite.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import contact_scenes  # noqa: E402

C = km._core.contact
DHAT2 = 0.01  # dhat = 0.1 [m]: the pairs below sit at distance 0.05
EPS_X = 1e-3  # 1e-3 |a1 - a0|^2 |b1 - b0|^2 for unit rest lengths
STEPS = 1e-3 / 2.0 ** np.arange(4)


def rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q


def parallel():
    # Exactly parallel and overlapping: (1, 0, 0) x (0.8, 0, 0) is exactly 0.
    return np.array([[0.0, 0, 0], [1, 0, 0], [0.1, 0.05, 0], [0.9, 0.05, 0]])


def parallel_rotated():
    # The same pair turned by a random rotation: parallel to rounding (s ~ 1e-33).
    return parallel() @ rotation(11).T + np.array([0.3, -0.2, 0.7])


def nearly_parallel():
    # Skew by theta with s = 0.64 sin^2(theta) = eps_x / 4: inside the mollified zone, the closest
    # points of the two lines interior to both segments (the line-line formula).
    theta = np.arcsin(np.sqrt(EPS_X / 4 / 0.64))
    c, d = np.array([0.5, 0.05, 0]), np.array([np.cos(theta), 0, np.sin(theta)])
    return np.array([[0.0, 0, 0], [1, 0, 0], c - 0.4 * d, c + 0.4 * d])


CASES = {"parallel": (parallel, 1), "parallel rotated": (parallel_rotated, 1), "nearly parallel": (nearly_parallel, 2)}


def errors(v, eps_x, directions):
    """Central-difference errors of the gradient and Hessian along `directions`, per step."""
    _, g, H = C.edge_edge_barrier(v, eps_x, DHAT2)
    eg, eh = [], []
    for h in STEPS:
        e1 = e2 = 0.0
        for u in directions:
            ep, gp, _ = C.edge_edge_barrier(v + h * u, eps_x, DHAT2)
            em, gm, _ = C.edge_edge_barrier(v - h * u, eps_x, DHAT2)
            e1 = max(e1, abs((ep - em) / (2 * h) - g @ u.ravel()))
            e2 = max(e2, np.abs((gp - gm) / (2 * h) - H @ u.ravel()).max())
        eg.append(e1)
        eh.append(e2)
    return np.array(eg), np.array(eh), g, H


def slope(err):
    return np.polyfit(np.log(STEPS), np.log(err), 1)[0]


def unit_directions(seed, count=6):
    u = np.random.default_rng(seed).normal(size=(count, 4, 3))
    return u / np.linalg.norm(u, axis=(1, 2), keepdims=True)


@pytest.mark.parametrize("case", sorted(CASES))
def test_mollified_edge_barrier_derivatives_converge_at_their_order(case):
    make, hessian_order = CASES[case]
    v = make()
    # The pair is active (closer than dhat: the barrier without mollifier is positive).
    assert C.edge_edge_barrier(v, 0.0, DHAT2)[0] > 0, case
    eg, eh, g, H = errors(v, EPS_X, unit_directions(1))
    # Rounding floor of the differences (energy ~1e-4, gradient ~1e-2 at most, divided by the
    # smallest step) is ~1e-13: far below every error measured here, so the slopes are truncation.
    assert eg.min() > 1e-13 and eh.min() > 1e-13, (case, eg, eh)
    assert slope(eg) >= 2 - 0.2, (case, "gradient", eg, slope(eg))
    assert slope(eh) >= hessian_order - 0.2, (case, "hessian", eh, slope(eh))
    # The errors are small against the quantities themselves (the largest step is 1e-3 on unit
    # edges): the finite differences see the derivative returned, not another.
    scale_g = max(np.abs(g).max(), np.abs(H).max() * STEPS[0])
    assert eg[-1] <= 1e-3 * scale_g, (case, eg, scale_g)
    assert eh[-1] <= 1e-2 * np.abs(H).max(), (case, eh, np.abs(H).max())
    # Structure: symmetric Hessian, translation invariance.
    assert np.abs(H - H.T).max() <= 1e-12 * np.abs(H).max()
    assert np.abs(g.reshape(4, 3).sum(0)).max() <= 1e-12 * max(np.abs(g).max(), 1e-300) + 1e-300
    assert np.abs(H @ np.tile([1.0, -2.0, 0.5], 4)).max() <= 1e-10 * np.abs(H).max()


def test_mollified_edge_barrier_vanishes_with_its_gradient_at_exactly_parallel_edges():
    e, g, H = C.edge_edge_barrier(parallel(), EPS_X, DHAT2)
    assert e == 0 and np.all(g == 0), (e, g)
    # The Hessian there is m'(0) b(d) Hess(s): not zero, positive semidefinite (Hess s = 2 J^T J).
    w = np.linalg.eigvalsh(H)
    assert w.max() > 0 and w.min() >= -1e-12 * w.max(), w


def test_mollifier_is_continuous_with_its_slope_at_the_threshold():
    # Across s = eps_x the term switches from m(s) b(d) to b(d): value and gradient must agree.
    v = nearly_parallel()
    s_of = lambda y: np.sum(np.cross(y[1] - y[0], y[3] - y[2]) ** 2)  # noqa: E731
    s = s_of(v)
    lo, hi = (C.edge_edge_barrier(v, eps_x, DHAT2) for eps_x in (s * (1 + 1e-9), s * (1 - 1e-9)))
    assert abs(lo[0] - hi[0]) <= 1e-12 * hi[0], (lo[0], hi[0])
    assert np.abs(lo[1] - hi[1]).max() <= 1e-7 * np.abs(hi[1]).max(), np.abs(lo[1] - hi[1]).max()


def test_unmollified_edge_barrier_fails_the_same_check_at_parallel_edges():
    # Without the mollifier (eps_x = 0) the gradient at the parallel pair is the one-sided
    # point-edge gradient; central differences see the average of both sides, so the error does
    # not shrink with the step: this is the kink the mollifier removes.
    v = parallel()
    eg, _, g, _ = errors(v, 0.0, unit_directions(1))
    assert slope(eg) < 0.5 and eg[-1] > 1e-2 * np.abs(g).max(), (eg, np.abs(g).max())


def clamp_psd(H):
    w, V = np.linalg.eigh(H)
    return (V * np.maximum(w, 0)) @ V.T


@pytest.mark.parametrize("case", sorted(CASES))
def test_projection_on_the_translation_free_subspace_equals_the_full_eigen_clamp(case):
    # The barrier term is invariant under translating its four vertices, so its Hessian vanishes
    # on translations; projecting its 9 x 9 restriction to their complement must give the
    # nearest PSD matrix of the full 12 x 12 one (to rounding of the eigen solves, ~1e-14
    # relative to the largest entry). Random skew pairs too, where the line-line formula holds.
    rng = np.random.default_rng(2)
    configs = [CASES[case][0]()]
    for _ in range(5):
        v = rng.normal(size=(4, 3))
        v[2:] = v[:2].mean(0) + rng.normal(size=(2, 3)) * 0.1 + np.array([0, 0, 0.03])
        configs.append(v)
    for v in configs:
        _, _, H = C.edge_edge_barrier(v, EPS_X, DHAT2)
        _, _, Hp = C.edge_edge_barrier(v, EPS_X, DHAT2, project=True)
        scale = max(np.abs(H).max(), 1e-300)
        assert np.abs(Hp - clamp_psd(H)).max() <= 1e-10 * scale, (case, np.abs(Hp - clamp_psd(H)).max(), scale)
        assert np.linalg.eigvalsh(Hp).min() >= -1e-12 * scale


def test_barrier_gradient_of_two_aligned_cubes_converges_under_central_differences():
    # Two axis-aligned cubes, the upper one shifted sideways by half a cell and resting 5 mm
    # above the lower (dhat = 1 cm): their horizontal edges are exactly parallel in pairs. With
    # the mollifier the barrier energy is C^1 along any line, so central differences of it
    # converge to the returned gradient at order >= 1 (order 2 where the line meets no region
    # boundary); a kink would leave an error that does not shrink. Asserted: slope >= 0.8 over
    # four halvings from 1e-5 m (measured: 1.0), and the error at the smallest step below 1e-3 of the directional derivative
    # scale |g| |u|.
    scene = km.contact.Scene(dhat=0.01)
    v, t = km.fem.box_mesh((0, 0, 0), (0.1, 0.1, 0.1), 2)
    scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    scene.add_solid(v + np.array([0.025, 0.105, 0.0]), t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    x = scene.x.copy()
    assert scene._core.constraint_count(x) > 0
    g = scene.barrier_gradient(x)
    rng = np.random.default_rng(8)
    steps = 1e-5 / 2.0 ** np.arange(4)
    for _ in range(3):
        u = rng.normal(size=x.shape)
        u /= np.linalg.norm(u)
        err = np.array([abs((scene.barrier_energy(x + h * u) - scene.barrier_energy(x - h * u)) / (2 * h) - np.sum(g * u))
                        for h in steps])
        scale = np.linalg.norm(g)
        floor = 1e-9 * scale  # far above rounding (energy 6e-7 x 1e-16 / 1.25e-6 ~ 1e-16 absolute)
        if err.max() <= floor:
            continue
        assert np.polyfit(np.log(steps), np.log(np.maximum(err, floor)), 1)[0] >= 0.8, (err, scale)
        assert err[-1] <= 1e-3 * scale, (err, scale)


@pytest.mark.slow  # about 10 s on a quiet machine (14 cloth steps twice), a minute on a busy one
def test_steps_are_bitwise_the_same_for_any_thread_count_and_after_a_resume():
    # The broad phase keeps refit trees between queries and the narrow phase, CCD and barrier
    # terms run in parallel; neither may change a result: candidates are ordered by primitive,
    # not by tree, and sums run in constraint order.
    before = km.get_num_threads()

    def run(threads):
        km.set_num_threads(threads)
        try:
            # The cloth draped on the sphere: enough points, edges, candidates (> 256) and
            # contacts (> 64) for every parallel loop to run on more than one thread.
            scene, dt = contact_scenes.cloth_scene(False, 12)
            for _ in range(10):
                scene.step(dt)
            assert scene._core.constraint_count(scene.x) > 64
            saved = scene.state()
            scene.step(dt)
            x = scene.x.copy()
            scene.set_state(saved)
            scene.step(dt)
            assert np.array_equal(x, scene.x), "a resumed step differs"
            return x
        finally:
            km.set_num_threads(before)

    assert np.array_equal(run(1), run(2))
