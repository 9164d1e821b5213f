"""Hardening: exact answers on periodic domains with body forces, rollback after a failing step,
NaN in state views, argument conversion (complex, C integer range, spacings), thread counts and
copying of simulation objects."""

import copy
import pickle
import re
import threading

import numpy as np
import pytest

import kinema as km

MS_X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])


# ------------------------------------------------------------------ periodic body forces
@pytest.mark.parametrize("shape, g", [((8, 8), [1.0, 0.0]), ((8, 6), [0.7, -2.0]), ((7, 8), [1.0, -0.5]),
                                      ((8, 8, 8), [0.0, 0.0, 1.5]), ((6, 8, 4), [1.0, -0.5, 2.0])])
@pytest.mark.parametrize("advection", ["semi_lagrangian", "maccormack"])
def test_periodic_gravity_gives_the_exact_uniform_flow(shape, g, advection):
    # On a periodic domain a uniform body force is divergence free: the exact solution is
    # u = g t everywhere with zero pressure gradient. Each face value is a sum of dt*g terms
    # (advection and viscosity return a uniform field unchanged up to rounding), so the error
    # is a few ulps of |g| t per step; 1e-12 covers 4 steps. (7, 8) is odd: the projection
    # falls back to CG there.
    f = km.grid.Fluid(shape, 0.1, boundary="periodic", gravity=g, advection=advection, tol=1e-10,
                      viscosity=0.01)
    dt, steps = 0.05, 4
    for _ in range(steps):
        f.step(dt)
    for c, comp in enumerate(f.velocity):
        np.testing.assert_allclose(comp, g[c] * dt * steps, rtol=0, atol=1e-12)
    assert np.abs(f.divergence()).max() < 1e-10


def test_periodic_buoyancy_of_a_uniform_density_is_uniform():
    # buoyancy of a uniform density is a uniform body force too (the cell-force path)
    f = km.grid.Fluid((8, 8), 0.1, boundary="periodic", density=True, buoyancy=(2.0, 0.0))
    f.density[...] = 0.5
    f.step(0.1)
    np.testing.assert_allclose(f.v, -2.0 * 0.5 * 0.1, atol=1e-12)
    np.testing.assert_allclose(f.u, 0.0, atol=1e-12)


# ------------------------------------------------------------------ rollback
def _snapshot(obj, names):
    return {n: np.array(getattr(obj, n), copy=True) for n in names} | {"time": obj.time}


def _assert_same(obj, snap):
    for n, a in snap.items():
        got = getattr(obj, n)
        if n == "time":
            assert got == a
        else:
            np.testing.assert_array_equal(got, a, err_msg=n)


def _stretched():
    return km.massspring.System(MS_X, [[0, 1], [1, 2]], stiffness=100.0, rest_length=0.5,
                                gravity=[0, -9.8, 0])


def test_rollback_massspring_after_divergence():
    s = _stretched()
    s.step(0.01, "symplectic", steps=3)
    # far beyond the explicit limit the step is refused before it runs, the state untouched
    x0 = s.x.copy()
    with pytest.raises(ValueError, match="unstable_dt"):
        s.step(1e100, "explicit", steps=50)
    np.testing.assert_array_equal(s.x, x0)
    # just below unstable_dt (above the true limit: warned) the explicit steps grow until they
    # overflow; the steps before the failing one stand, the failing one is undone: the state is
    # that of a replay stopped just before it
    dt = 0.99 * s.unstable_dt
    with pytest.warns(RuntimeWarning, match="explicit_dt_limit"), pytest.raises(km.DivergenceError):
        s.step(dt, "explicit", steps=5000)
    ref = _stretched()
    ref.step(0.01, "symplectic", steps=3)
    for _ in range(5000):
        before = ref.x.copy(), ref.v.copy(), ref.time
        try:
            with pytest.warns(RuntimeWarning, match="explicit_dt_limit"):
                ref.step(dt, "explicit")
        except km.DivergenceError:
            break
    else:
        pytest.fail("the replay did not diverge")
    np.testing.assert_array_equal(ref.x, before[0])  # one step's rollback, checked by hand
    np.testing.assert_array_equal(ref.v, before[1])
    assert ref.time == before[2]
    assert np.isfinite(s.x).all() and np.isfinite(s.v).all()
    np.testing.assert_array_equal(s.x, ref.x)
    np.testing.assert_array_equal(s.v, ref.v)
    assert s.time == ref.time
    # the advice (a smaller dt) can be taken and the run goes on
    s = _stretched()
    s.step(0.01, "symplectic", steps=3)
    snap = _snapshot(s, ["x", "v"])
    with pytest.raises(ValueError, match="unstable_dt"):
        s.step(1e308, "explicit")  # refused (v + dt f would overflow in the first step)
    _assert_same(s, snap)
    s.step(1e-3, "implicit")
    assert s.time == pytest.approx(0.031)


def test_rollback_grid_after_divergence():
    f = km.grid.Fluid((8, 8), 0.1, gravity=[0, -9.8])
    f.step(0.01)
    snap = _snapshot(f, ["u", "v", "pressure"])
    with pytest.raises(km.KinemaError):
        f.step(1e308)  # gravity * dt overflows on the way
    _assert_same(f, snap)
    f.step(0.01)
    assert f.time == pytest.approx(0.02) and f.steps == 2


def test_rollback_fem_after_failed_step():
    v, e = km.fem.rectangle_mesh([0, 0], [1, 1], (3, 3))
    b = km.fem.Body(v, e, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3, fixed=[0, 1, 2, 3],
                    gravity=[0, -9.8])
    b.step(0.01)
    snap = _snapshot(b, ["x", "v"])
    with pytest.raises(km.KinemaError):
        b.step(1e200, max_newton=2)
    _assert_same(b, snap)
    with pytest.raises(ValueError, match="unstable_dt"):  # refused before stepping
        b.step(1e200, "symplectic")
    _assert_same(b, snap)
    b.step(0.01)
    assert b.time == pytest.approx(0.02)


def test_rollback_mpm_after_failed_step():
    sim = km.mpm.Simulation((16, 16), 1 / 16, gravity=[0, -9.8])
    sim.add_particles(km.mpm.block([0.3, 0.3], [0.6, 0.6], 1 / 32), "elastic", density=1e3,
                      youngs_modulus=1e4, poisson_ratio=0.3)
    sim.step(1e-3)
    snap = _snapshot(sim, ["x", "v", "F", "C"])
    with pytest.warns(RuntimeWarning, match="cfl_dt"), pytest.raises(km.DivergenceError):
        sim.step(10.0)  # a particle would cross many cells in one step
    _assert_same(sim, snap)
    sim.step(1e-3)
    assert sim.time == pytest.approx(2e-3)


def test_rollback_nbody_after_failed_step():
    # the step fails in its second force evaluation, after the kick and the drift changed v and
    # x: the state must be that before the step
    x, v, m = km.nbody.plummer(50, seed=3)
    s = km.nbody.System(x, v, m, softening=0.05)
    s.step(1e-3)
    snap = _snapshot(s, ["x", "v"])
    forces = s.accelerations
    calls = []

    def failing():
        calls.append(1)
        if len(calls) == 2:
            raise km.DivergenceError("accelerations: injected failure")
        return forces()

    s.accelerations = failing
    s._acc = None  # the step then evaluates the forces twice: before the kick, after the drift
    with pytest.raises(km.DivergenceError, match="injected"):
        s.step(1e-3)
    _assert_same(s, snap)
    assert s.steps == 1
    del s.accelerations
    s.step(1e-3)
    assert s.steps == 2 and np.isfinite(s.x).all()


def test_rollback_sph_after_failed_step():
    x = km.sph.block([0, 0], [0.1, 0.1], 0.02) + 0.01
    f = km.sph.Fluid(x, 0.02, gravity=[0, -9.8], domain=([0, 0], [0.2, 0.2]))
    f.step(1e-4)
    snap = _snapshot(f, ["x", "v", "ids"])
    f.v[0, 0] = np.nan
    with pytest.raises(km.DivergenceError):
        f.step(1e-4)
    f.v[0, 0] = snap["v"][0, 0]
    _assert_same(f, snap)
    f.step(1e-4)


# ------------------------------------------------------------------ NaN in state views
def test_queries_after_nan_in_a_view_raise():
    g = km.grid.Fluid((8, 8), 0.1)
    g.u[3, 3] = np.nan
    for query in (lambda: g.velocity_at([[0.35, 0.35]]), g.divergence, g.kinetic_energy, g.max_speed):
        with pytest.raises(km.DivergenceError, match="non-finite"):
            query()
    s = km.massspring.System(MS_X, [[0, 1]], stiffness=1.0)
    s.x[0, 0] = np.nan
    with pytest.raises(km.DivergenceError):
        s.energy()
    v, e = km.fem.rectangle_mesh([0, 0], [1, 1], (2, 2))
    b = km.fem.Body(v, e, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3)
    b.v[0, 0] = np.inf
    with pytest.raises(km.DivergenceError):
        b.energy()


def test_sph_ids_are_checked_before_a_step():
    f = km.sph.Fluid(km.sph.block([0, 0], [0.1, 0.1], 0.02), 0.02, gravity=(0, -9.81))
    f.ids[:] = 7
    with pytest.raises(ValueError, match="ids"):
        f.step(1e-4)
    f.ids[:] = np.arange(f.n)
    f.step(1e-4)


# ------------------------------------------------------------------ degenerate legal systems
def test_massspring_without_springs_is_finite():
    s = km.massspring.System(MS_X, np.zeros((0, 2), int), stiffness=1.0, gravity=[0, -9.8, 0])
    assert np.isfinite(s.energy())
    s.step(0.1, "symplectic")
    np.testing.assert_allclose(s.v[:, 1], -0.98)
    z = km.massspring.System(MS_X, [[0, 1]], stiffness=0.0)
    z.step(0.01)
    assert np.isfinite(z.energy())


def test_fmm_scalar_charges_and_a_cluster_with_far_points():
    rng = np.random.default_rng(1)
    x = rng.random((30, 2))
    np.testing.assert_allclose(km.fmm.laplace2d(x, 2.0), km.fmm.direct2d(x, np.full(30, 2.0)), rtol=1e-8)
    pts = np.vstack([rng.random((300, 2)) * 1e-9, [[1e3, 1e3], [-1e3, 5.0]]])
    q = rng.standard_normal(302)
    phi = km.fmm.laplace2d(pts, q, eps=1e-10)
    ref = km.fmm.direct2d(pts, q)
    assert np.isfinite(phi).all()
    assert np.linalg.norm(phi - ref) <= 1e-9 * np.linalg.norm(ref)


def test_empty_render_scene_shows_the_sky():
    cam = km.render.Camera([0, 0, 5], [0, 0, 0], width=8, height=6)
    img = km.render.Scene().render(cam, spp=2)
    assert img.shape == (6, 8, 3) and np.isfinite(img).all() and img.max() > 0


# ------------------------------------------------------------------ argument conversion
@pytest.mark.parametrize("call, name", [
    (lambda: km.poisson.solve(np.ones((8, 8)) + 0j, 0.1), "f"),
    (lambda: km.grid.Fluid((8, 8), 0.1, gravity=[1j, 0]), "gravity"),
    (lambda: km.poisson.Solver((8, 8), 0.1, shift=1j), "shift"),
    (lambda: km.fmm.laplace2d(np.ones((3, 2)), np.ones(3) * 1j), "charges"),
])
def test_complex_input_is_refused(call, name):
    with pytest.raises(ValueError, match=name):
        call()


@pytest.mark.parametrize("call, name", [
    (lambda: km.poisson.solve(np.ones((8, 8)), 1 / 8, max_iter=2**63), "max_iter"),
    (lambda: km.grid.Fluid((8, 8), 0.1, max_iter=2**64), "max_iter"),
    (lambda: km.massspring.System(MS_X, [[0, 1]], stiffness=1.0).step(0.01, steps=2**70), "steps"),
    (lambda: km.grid.Fluid((8, 2**70), 0.1), "shape"),
    (lambda: km.grid.Fluid((8, 8), 5e-324), "h"),
    (lambda: km.grid.Fluid((8, 8), 2**1100), "h"),
    (lambda: km.sph.Fluid(km.sph.block([0, 0], [0.1, 0.1], 0.02), 5e-324), "spacing"),
    (lambda: km.poisson.solve(np.ones((8, 8)), 1e-308), "h"),
    (lambda: km.set_num_threads(100000), "n"),
    (lambda: km.set_num_threads(2**31 - 1), "n"),
    (lambda: km.set_num_threads(2**80), "n"),
])
def test_odd_values_give_one_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        call()


def _scene_with_a_moving_plane():
    scene = km.contact.Scene()
    v, t = km.fem.box_mesh((0, 0.01, 0), (0.1, 0.11, 0.1), 1)
    scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.3, density=1000)
    scene.add_collider("plane", velocity=(0, 1, 0))
    return scene


@pytest.mark.parametrize("index, time, name", [(1, None, "index"), (-2, None, "index"), (0.0, None, "index"),
                                               (0, float("nan"), "time"), (0, float("inf"), "time"),
                                               (0, "soon", "time")])
def test_collider_positions_names_a_bad_index_or_time(index, time, name):
    """(Its index was an IndexError of a list, a NaN time a RuntimeWarning and a message about
    turning the plane's normal.)"""
    scene = _scene_with_a_moving_plane()
    with pytest.raises(ValueError, match=f"^{name}: "):
        scene.collider_positions(index, time)
    np.testing.assert_array_equal(scene.collider_positions(-1, 0.5), [[0.0, 0.5, 0.0]])
    with pytest.raises(ValueError, match="^index: the scene has no colliders"):
        km.contact.Scene().collider_positions(0)


# ------------------------------------------------------------------ threads and copies
def test_set_num_threads_applies_to_worker_threads():
    before = km.get_num_threads()
    try:
        km.set_num_threads(1)
        seen = []
        t = threading.Thread(target=lambda: seen.append(km.get_num_threads()))
        t.start()
        t.join()
        assert seen == [1]
    finally:
        km.set_num_threads(before)


@pytest.mark.parametrize("make", [
    lambda: km.grid.Fluid((8, 8), 0.1),
    lambda: km.massspring.System(MS_X, [[0, 1]], stiffness=1.0),
    lambda: km.sph.Fluid(km.sph.block([0, 0], [0.1, 0.1], 0.02), 0.02),
    lambda: km.render.Scene(),
    lambda: km.poisson.Solver((8, 8), 0.1),
])
def test_copying_a_simulation_object_is_a_clear_error(make):
    obj = make()
    for how in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="cannot be copied"):
            how(obj)


# ------------------------------------------------------------------ Ctrl-C
def test_a_large_cholesky_answers_ctrl_c(ctrl_c_delay):
    # a 48^3 Poisson matrix takes seconds to factorise; CHOLMOD runs on its own thread and the
    # caller answers Ctrl-C within the 0.1 s poll (1 s allowed on a loaded machine)
    A = km.poisson.matrix((48, 48, 48), 1 / 48)
    assert ctrl_c_delay(lambda: km.sparse.cholesky(A), after=0.3) < 1.0
    # the abandoned factorisation does not disturb the next one
    F = km.sparse.cholesky(km.poisson.matrix((6, 6), 0.1))
    assert np.isfinite(F.solve(np.ones(36))).all()
