"""km.fmm.laplace3d: the 3D FMM against the exact sum for eps from 1e-3 to 1e-12 on uniform and
clustered points (Plummer sphere, thin shell, torus surface), gradients against central finite
differences, separate targets, degenerate input, determinism across thread counts, Ctrl-C, bad
input, and (slow) the O(N) scaling fitted over 1e4..1e6."""

import time

import numpy as np
import pytest

import kinema as km


def distribution(name, n, seed=0):
    rng = np.random.default_rng(seed)
    if name == "uniform":
        return rng.random((n, 3))
    if name == "plummer":
        x, _, _ = km.nbody.plummer(n, seed=seed)
        return x
    if name == "shell":  # a sphere of radius 1 and thickness 1e-3
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        return d * (1 + 1e-3 * rng.random(n))[:, None]
    if name == "torus":  # points on a surface
        u, v = rng.uniform(0, 2 * np.pi, (2, n))
        return np.c_[(1 + 0.3 * np.cos(v)) * np.cos(u), (1 + 0.3 * np.cos(v)) * np.sin(u), 0.3 * np.sin(v)]
    raise ValueError(name)


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


# Sizes above the direct-sum crossover (so the FMM runs) with trees 3-9 levels deep.
N = 6000


@pytest.mark.parametrize("eps", [1e-3, 1e-6, 1e-9, 1e-12])
@pytest.mark.parametrize("dist", ["uniform", "plummer", "shell", "torus"])
def test_self_interaction_matches_direct(dist, eps):
    x = distribution(dist, N)
    q = np.random.default_rng(1).uniform(-1, 1, N)  # mixed signs: cancellation makes phi small
    phi, grad = km.fmm.laplace3d(x, q, eps=eps, gradient=True)
    info = km.fmm.last_info()
    assert not info["direct"] and info["depth"] >= 2, info
    phi_ref, grad_ref = km.fmm.direct3d(x, q, gradient=True)
    e_phi, e_grad = rel(phi, phi_ref), rel(grad, grad_ref)
    assert e_phi < eps, f"{dist}: phi relative error {e_phi:.3e} above eps {eps:g} (order {info['order']})"
    # The contract bounds phi; the gradient (one derivative more) is documented within 20 eps.
    assert e_grad < 20 * eps, f"{dist}: gradient relative error {e_grad:.3e} above 20 eps"


@pytest.mark.parametrize("eps", [1e-6, 1e-9, 1e-10, 1e-12])
@pytest.mark.parametrize("flat", ["plane", "line", "two_planes"])
def test_axis_aligned_flat_sets_meet_eps(flat, eps):
    # Points on a plane z = 0 (or a line) sat on the faces between boxes at every level of a
    # centred tree, each at its worst distance from its box centre: the error fell ~0.16
    # decades per order instead of ~0.3 and missed eps by 1.4x at 1e-9, 3x at 1e-10, 18x at
    # 1e-12. Two parallel planes: one at the centre, one at the root's faces.
    rng = np.random.default_rng(3)
    u = rng.random((N, 2))
    x = {"plane": np.c_[u, np.zeros(N)],
         "line": np.c_[u[:, 0], np.zeros(N), np.zeros(N)],
         "two_planes": np.c_[u, (np.arange(N) % 2).astype(float)]}[flat]
    q = np.random.default_rng(4).uniform(-1, 1, N)
    phi, grad = km.fmm.laplace3d(x, q, eps=eps, gradient=True)
    assert not km.fmm.last_info()["direct"]
    phi_ref, grad_ref = km.fmm.direct3d(x, q, gradient=True)
    e_phi, e_grad = rel(phi, phi_ref), rel(grad, grad_ref)
    assert e_phi < eps, f"{flat}: phi relative error {e_phi:.3e} above eps {eps:g}"
    assert e_grad < 20 * eps, f"{flat}: gradient relative error {e_grad:.3e} above 20 eps"


@pytest.mark.parametrize("eps", [10.0 ** -k for k in range(3, 13)])
@pytest.mark.parametrize("dist", ["uniform", "plummer"])
def test_every_decade_of_eps_is_met(dist, eps):
    x = distribution(dist, N, seed=7)
    q = np.random.default_rng(8).uniform(-1, 1, N)
    phi = km.fmm.laplace3d(x, q, eps=eps)
    e = rel(phi, km.fmm.direct3d(x, q))
    assert e < eps, f"{dist}: phi relative error {e:.3e} above eps {eps:g} (order {km.fmm.last_info()['order']})"


@pytest.mark.parametrize("order", [3, 8, 14, 26])
def test_rotated_m2l_agrees_with_dense_to_rounding(order):
    # The rotation-based M2L (rotate to z, translate along z, rotate back: O(p^3)) and the dense
    # O(p^4) matrices are two factorisations of one operator: the whole FMM (clustered points,
    # so every pass and the adaptive lists run) must agree to rounding, far below any eps.
    # Each operator agrees to ~1e-16 relative (the C++ test); with the mixed-sign charges'
    # cancellation (||sum |q|/r|| / ||phi|| ~ 1e2 here) the bound is ~1e-14; measured 2-3e-16.
    x = distribution("plummer", N, seed=5)
    q = np.random.default_rng(6).uniform(-1, 1, N)
    phi_d, grad_d = km.fmm.laplace3d(x, q, order=order, gradient=True, m2l="dense")
    assert km.fmm.last_info()["m2l"] == "dense"
    phi_r, grad_r = km.fmm.laplace3d(x, q, order=order, gradient=True, m2l="rotation")
    assert km.fmm.last_info()["m2l"] == "rotation"
    assert rel(phi_r, phi_d) < 1e-14
    assert rel(grad_r, grad_d) < 1e-14


@pytest.mark.parametrize("eps", [1e-4, 1e-8])
def test_separate_targets_match_direct(eps):
    x = distribution("plummer", 5000, seed=2)
    y = distribution("uniform", 3000, seed=3) * 4 - 2
    q = np.random.default_rng(4).uniform(0, 1, len(x))
    phi, grad = km.fmm.laplace3d(x, q, y, eps=eps, gradient=True)
    phi_ref, grad_ref = km.fmm.direct3d(x, q, y, gradient=True)
    assert rel(phi, phi_ref) < eps
    assert rel(grad, grad_ref) < 20 * eps


@pytest.mark.parametrize("eps", [1e-3, 1e-6])
@pytest.mark.parametrize("separate", [False, True])
def test_ragged_tree_meets_eps(eps, separate):
    # A leaf size at the mean count of a level (8000 / 64 = 125) splits about half of its boxes:
    # big leaves beside split neighbours, with W and X lists whose small boxes are summed
    # directly (both directions) and the larger ones through M2P / P2L.
    x = distribution("uniform", 8000, seed=5)
    y = distribution("uniform", 8000, seed=6) if separate else None
    q = np.random.default_rng(7).uniform(-1, 1, len(x))
    phi, grad = km.fmm.laplace3d(x, q, y, eps=eps, gradient=True, leaf_size=125)
    info = km.fmm.last_info()
    assert info["depth"] == 3 and 1 + 8 + 64 < info["boxes"] < 1 + 8 + 64 + 512, info  # ragged level 3
    phi_ref, grad_ref = km.fmm.direct3d(x, q, y, gradient=True)
    assert rel(phi, phi_ref) < eps
    assert rel(grad, grad_ref) < 20 * eps


def test_direct_sum_is_exact_and_leaves_out_zero_distance_pairs():
    x = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2, 0], [1.0, 0, 0]])  # a duplicate point
    q = np.array([1.0, 2.0, 3.0, 4.0])
    phi, grad = km.fmm.direct3d(x, q, gradient=True)
    # by hand: phi_0 = 2/1 + 3/2 + 4/1; point 1 and 3 do not see each other
    assert phi[0] == pytest.approx(7.5, rel=1e-15)
    assert phi[1] == pytest.approx(1 + 3 / np.sqrt(5), rel=1e-15)
    assert grad[0] == pytest.approx([6.0, 0.75, 0.0], rel=1e-15)  # -q (x - y)/r^3 summed


def test_gradient_against_central_differences():
    x = distribution("torus", 8000, seed=5)  # the surface stays >= 0.4 from the targets
    q = np.random.default_rng(6).uniform(0.5, 1, len(x))
    rng = np.random.default_rng(7)
    y = np.c_[rng.uniform(-0.3, 0.3, (20, 2)) / np.sqrt(2), rng.uniform(-0.5, 0.5, 20)]
    _, grad = km.fmm.laplace3d(x, q, y, eps=1e-10, gradient=True)
    # central differences: error ~ h^2 |phi"'| / 6 ~ h^2 / r^2 |grad| < 1e-7 |grad| for r >= 0.4
    h = 1e-4
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (km.fmm.laplace3d(x, q, y + e, eps=1e-10) - km.fmm.laplace3d(x, q, y - e, eps=1e-10)) / (2 * h)
        err = np.abs(fd - grad[:, k]).max() / np.abs(grad).max()
        assert err < 1e-6, f"d/dx{k}: finite-difference mismatch {err:.2e}"


def test_translation_and_scaling_invariance():
    x = distribution("shell", 6000)
    q = np.random.default_rng(8).standard_normal(len(x))
    phi = km.fmm.laplace3d(x, q, eps=1e-8)
    # phi scales as 1/L; the shift is small enough that rounding the shifted coordinates moves
    # the closest pairs (~1e-7 apart after scaling) by < 1e-11 relative
    moved = km.fmm.laplace3d(x * 1e-3 + [5e-3, -7e-3, 1e-3], q, eps=1e-8) * 1e-3
    assert rel(moved, phi) < 2e-8  # both within eps of the same exact sum


def test_deterministic_for_any_thread_count():
    x = distribution("plummer", 20000)
    q = np.random.default_rng(9).uniform(-1, 1, len(x))
    before = km.get_num_threads()
    try:
        km.set_num_threads(1)
        a = km.fmm.laplace3d(x, q, eps=1e-6, gradient=True)
        km.set_num_threads(2)
        b = km.fmm.laplace3d(x, q, eps=1e-6, gradient=True)
        c = km.fmm.laplace3d(x, q, eps=1e-6, gradient=True)
    finally:
        km.set_num_threads(before)
    for u, v in ((a, b), (b, c)):
        assert np.array_equal(u[0], v[0]) and np.array_equal(u[1], v[1])


def test_degenerate_inputs():
    assert km.fmm.laplace3d(np.zeros((0, 3)), np.zeros(0)).shape == (0,)
    phi = km.fmm.laplace3d(np.zeros((0, 3)), np.zeros(0), np.ones((4, 3)))
    assert np.array_equal(phi, np.zeros(4))
    # many coincident points (cannot be split by the tree) and a far one
    x = np.r_[np.zeros((3000, 3)), [[1.0, 1.0, 1.0]]]
    q = np.ones(len(x))
    phi = km.fmm.laplace3d(x, q, eps=1e-8, order=8)
    assert phi[0] == pytest.approx(1 / np.sqrt(3), rel=1e-12)
    assert phi[-1] == pytest.approx(3000 / np.sqrt(3), rel=1e-8)


@pytest.mark.parametrize("d", [1e-200, 1e-160, 1e-120, 1e120, 1e160, 1e200])
@pytest.mark.parametrize("path", ["direct", "fmm"])
def test_distinct_points_are_summed_however_close_or_far(d, path):
    # Two unit charges d apart along a skew direction: phi = 1/d at each, though d^2 under- or
    # overflows. A pair at distance 0 is the only one left out; here none is. Beside them a
    # cloud of zero charges makes the FMM run its near field (order given) on the same pair;
    # 1/d is computed from the scaled difference, so phi is exact to a few roundings (1e-14).
    e = np.array([1.0, 2.0, 2.0]) / 3
    cloud = np.random.default_rng(1).random((1000, 3)) * d
    x = np.r_[[np.zeros(3), d * e], cloud]
    q = np.r_[1.0, 1.0, np.zeros(len(cloud))]
    kw = {} if path == "direct" else dict(order=6)
    phi = km.fmm.laplace3d(x, q, **kw)
    assert km.fmm.last_info()["direct"] == (path == "direct")
    assert km.fmm.last_info()["coincident"] == 0
    assert phi[:2] == pytest.approx([1 / d, 1 / d], rel=1e-14)
    target = km.fmm.laplace3d(x, q, x[:1] + 0.5 * d * e, **kw)  # halfway: 2/d + 2/d
    assert target[0] == pytest.approx(4 / d, rel=1e-14)
    if d > 1e-150:  # 1/d^2 representable
        # grad at x_0 = -(x_0 - x_1)/d^3 = e/d^2 (the far points' 1/d^2 underflows to 0)
        _, g = km.fmm.laplace3d(x, q, gradient=True, **kw)
        assert g[0] == pytest.approx(e / d / d, rel=1e-14, abs=1e-300)
    else:  # the gradient 1/d^2 is beyond double: said, not returned as 0
        with pytest.raises(ValueError, match="gradient"):
            km.fmm.laplace3d(x, q, gradient=True, **kw)


@pytest.mark.parametrize("path", ["direct", "fmm"])
def test_coincident_pairs_are_left_out_and_counted(path):
    # A rule, not an accident: sources at exactly the same position are left out of each
    # other's sums (1/0) and counted in last_info()["coincident"] (pairs both charged), in
    # the direct sum and in the FMM's vectorised near field alike.
    rng = np.random.default_rng(2)
    x = rng.random((1200, 3))  # below the direct-sum crossover
    x[10] = x[11] = x[12] = x[5]  # a group of four: 4 * 3 ordered pairs
    x[20] = x[21]                  # two more ordered pairs, but 20 has no charge: none
    q = rng.random(len(x)) + 0.5
    q[20] = 0.0
    kw = {} if path == "direct" else dict(order=10)
    phi = km.fmm.laplace3d(x, q, **kw)
    assert km.fmm.last_info()["direct"] == (path == "direct")
    assert km.fmm.last_info()["coincident"] == 12
    distinct = np.r_[0:5, 6:10, 13:len(x)]
    d = np.linalg.norm(x[distinct] - x[5], axis=1)
    expected = np.sum(q[distinct] / d)  # at x_5: every source but itself and its three copies
    assert phi[5] == pytest.approx(expected, rel=1e-9)
    # targets given: a target on a charged source leaves that source out and counts it (x_5
    # sits on four; x_20 = x_21 on source 21 only, source 20 having no charge)
    km.fmm.laplace3d(x, q, x[[5, 20, 21]], **kw)
    assert km.fmm.last_info()["coincident"] == 4 + 1 + 1


@pytest.mark.parametrize("kwargs, match", [
    (dict(sources=np.zeros((4, 2)), charges=np.ones(4)), "sources"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(3)), "charges"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), targets=np.zeros(3)), "targets"),
    (dict(sources=np.full((4, 3), np.nan), charges=np.ones(4)), "sources"),
    (dict(sources=np.zeros((4, 3)), charges=[1, 2, np.inf, 4]), "charges"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), eps=0), "eps"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), eps="x"), "eps"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), order=41), "order"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), leaf_size=0), "leaf_size"),
    (dict(sources=np.zeros((4, 3)), charges=np.ones(4), m2l="fft"), "m2l"),
    (dict(sources=np.zeros((4, 3), complex), charges=np.ones(4)), "sources"),
])
def test_bad_input_raises_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        km.fmm.laplace3d(**kwargs)


def test_ctrl_c_stops_a_long_call(ctrl_c_delay):
    # The call (N = 1e6, eps 1e-9) costs ~15 CPU seconds. Between two interrupt checks it runs
    # at most one tree level's partition, 1024 boxes' P2M, one offset's M2L on one level, or
    # 256 leaves' evaluation or near-field tasks: each < 0.2 CPU s (1/256 of the leaf pass, the
    # largest), and the poll runs every 0.1 s of wall time (<= 0.2 CPU s on two threads). So
    # the CPU seconds from the signal to the exception stay below 0.4 + unwinding: bound 1.5,
    # a tenth of what a call that ignored Ctrl-C would spend. CPU seconds, not wall: other
    # processes' load stretches the wall time of the same work (2.6 and 3.8 s were seen).
    x = np.random.default_rng(0).random((1_000_000, 3))
    q = np.ones(len(x))
    cpu = ctrl_c_delay(lambda: km.fmm.laplace3d(x, q, eps=1e-9), after=0.5, clock=time.process_time)
    assert cpu < 1.5, f"{cpu:.2f} CPU s spent after Ctrl-C"


@pytest.mark.slow
def test_linear_scaling():
    """The work over N = 1e4..1e6 (uniform, eps 1e-6) fitted as N^k: k within 0.2 of 1. The
    work is the least CPU time of three calls on one thread: other processes' load stretches
    wall time (and scheduling inflates it unevenly across sizes), not the CPU seconds of one
    thread's own work, so a cost growing as N^1.2 or faster still fails."""
    ns = [10_000, 40_000, 160_000, 640_000, 1_000_000]
    times = []
    before = km.get_num_threads()
    try:
        km.set_num_threads(1)
        for n in ns:
            x = np.random.default_rng(n).random((n, 3))
            q = np.ones(n)
            best = np.inf
            for _ in range(3):
                t = time.process_time()
                km.fmm.laplace3d(x, q, eps=1e-6)
                best = min(best, time.process_time() - t)
            times.append(best)
    finally:
        km.set_num_threads(before)
    k = np.polyfit(np.log(ns), np.log(times), 1)[0]
    assert abs(k - 1) < 0.2, f"fitted exponent {k:.2f} (CPU seconds {times})"


def test_near_field_beyond_the_float_estimate_range_falls_back_exactly():
    # Coordinates of size 1e19: squared distances up to ~1e38 exceed the range of the float
    # reciprocal square root (1e36), so the vectorised near field (one-way and mutual, the
    # targets being the sources) hands those leaves to the exact kernel.
    x = np.random.default_rng(12).random((3000, 3)) * 1e19
    q = np.random.default_rng(13).uniform(-1, 1, 3000)
    phi, grad = km.fmm.laplace3d(x, q, eps=1e-8, gradient=True)
    ref_phi, ref_grad = km.fmm.direct3d(x, q, gradient=True)
    assert not km.fmm.last_info()["direct"]
    assert rel(phi, ref_phi) < 1e-8 and rel(grad, ref_grad) < 1e-7
