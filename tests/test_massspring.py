"""km.massspring: the harmonic oscillator's period, the energy behaviour of explicit,
symplectic and implicit Euler, stability far beyond the explicit limit, cloth topology,
zero-copy state views and bad input."""

import math

import numpy as np
import pytest

import kinema as km


def oscillator(amplitude=0.1, k=4.0, m=0.25, L=1.0):
    # Vertex 0 fixed, vertex 1 on a spring of rest length L: omega = sqrt(k/m) = 4 rad/s.
    x = np.array([[0.0, 0.0], [L + amplitude, 0.0]])
    return km.massspring.System(x, [[0, 1]], stiffness=k, mass=m, rest_length=L, fixed=[0])


def test_oscillator_period():
    sys = oscillator()
    period = 2 * math.pi * math.sqrt(0.25 / 4.0)
    dt = period / 2000
    crossings, prev = [], sys.x[1, 0] - 1.0
    for n in range(1, 6000):
        sys.step(dt, "symplectic")
        cur = sys.x[1, 0] - 1.0
        if prev > 0 >= cur:  # downward zero crossings, linearly interpolated
            crossings.append((n - 1 + prev / (prev - cur)) * dt)
        prev = cur
    measured = np.diff(crossings).mean()
    assert abs(measured - period) < 1e-4 * period, f"period {measured}, expected {period}"


def test_explicit_energy_grows_symplectic_stays_bounded():
    period = 2 * math.pi * math.sqrt(0.25 / 4.0)
    dt = period / 40
    energies = {}
    for integrator in ("explicit", "symplectic"):
        sys = oscillator()
        e0 = sys.energy()
        e = [sys.energy()]
        for _ in range(400):
            sys.step(dt, integrator)
            e.append(sys.energy())
        energies[integrator] = np.array(e) / e0
    # Explicit Euler multiplies the energy by (1 + (omega dt)^2) per step: ~ e^(400*0.0247) here.
    assert energies["explicit"][-1] > 100, energies["explicit"][-1]
    # Symplectic Euler conserves a modified energy: the true one oscillates by O(omega dt).
    assert np.abs(energies["symplectic"] - 1).max() < 0.2, np.abs(energies["symplectic"] - 1).max()


def hanging_cloth(n=12, stiffness=1e4, **kw):
    x, springs = km.massspring.cloth(n, n, 1.0)
    x = x[:, [0, 2, 1]].copy()  # hang in the x-z plane
    x[:, 2] *= -1
    fixed = [0, (n - 1) * n]  # the two top corners
    return km.massspring.System(x, springs, stiffness=stiffness, mass=1.0 / n**2, fixed=fixed,
                                gravity=(0, 0, -9.81), **kw)


def test_implicit_stable_far_beyond_explicit_limit():
    sys = hanging_cloth(stiffness=1e5)
    dt = 1 / 30
    assert dt > 50 * sys.explicit_dt_limit, sys.explicit_dt_limit
    e0 = sys.energy()
    for _ in range(60):
        sys.step(dt, "implicit")
        assert np.isfinite(sys.x).all()
        assert sys.energy() <= e0 + 1e-9 * abs(e0), "backward Euler must not gain energy"
    # The same step explicitly is refused before it runs (beyond unstable_dt every explicit step
    # is unstable); explicit Euler grows at every dt, so a long run below the limit blows up,
    # reported as a DivergenceError, not NaN.
    exp = hanging_cloth(stiffness=1e5)
    with pytest.raises(ValueError, match="unstable_dt"):
        exp.step(dt, "explicit", steps=200)
    with pytest.raises(km.DivergenceError, match="dt"):
        exp.step(0.9 * exp.explicit_dt_limit, "explicit", steps=20000)


def test_long_implicit_run_never_gains_energy():
    sys = hanging_cloth(n=16, stiffness=1e4)
    dt = 1 / 30
    e = [sys.energy()]
    for _ in range(1200):  # 40 s
        sys.step(dt)
        e.append(sys.energy())
    rise = np.diff(e).max()
    assert rise <= 1e-9 * abs(e[0]), f"energy rose by {rise:.2e} in one step"


def test_implicit_cg_matches_cholmod_and_runs_are_deterministic():
    a, b, c = hanging_cloth(), hanging_cloth(), hanging_cloth()
    for _ in range(5):
        a.step(1 / 60)
        b.step(1 / 60, linear_solver="cg", cg_tol=1e-12)
        c.step(1 / 60)
    assert np.abs(a.x - b.x).max() < 1e-8
    assert np.array_equal(a.x, c.x), "two identical runs differ"


def test_trapezoid_beta_damps_less_than_backward_euler():
    dissipated = {}
    for beta in (1.0, 0.5):
        sys = oscillator()
        e0 = sys.energy()
        sys.step(0.05, "implicit", beta=beta, steps=100)
        dissipated[beta] = 1 - sys.energy() / e0
    assert dissipated[0.5] < 0.9 * dissipated[1.0], dissipated


def test_damping_and_stiff_springs_stay_finite():
    sys = hanging_cloth(stiffness=1e8, damping=1.0)
    sys.step(1 / 30, "implicit", steps=10)
    assert np.isfinite(sys.x).all() and np.isfinite(sys.v).all()


def test_cloth_topology():
    nx, ny = 5, 4
    x, springs, kinds = km.massspring.cloth(nx, ny, (2.0, 1.5), return_kinds=True)
    assert x.shape == (nx * ny, 3)
    assert np.allclose(x.max(axis=0), [2.0, 1.5, 0.0])
    counts = np.bincount(kinds)
    assert counts[0] == nx * (ny - 1) + ny * (nx - 1)
    assert counts[1] == 2 * (nx - 1) * (ny - 1)
    assert counts[2] == (nx - 2) * ny + nx * (ny - 2)
    x2, _ = km.massspring.cloth(3, 3, 1.0, dim=2)
    assert x2.shape == (9, 2)


def test_state_views_are_zero_copy():
    sys = oscillator()
    x = sys.x
    x[1, 0] = 1.0  # at rest length: no force
    sys.step(0.01, "symplectic")
    assert abs(sys.v[1, 0]) < 1e-15
    del sys
    assert x[1, 0] == 1.0  # the view keeps the system alive


@pytest.mark.parametrize("kwargs, match", [
    (dict(x=np.zeros((3, 4))), "x: expected shape"),
    (dict(springs=[[0, 1, 2]]), "springs: expected shape"),
    (dict(springs=[[0, 5]]), "springs: index 5"),
    (dict(springs=[[1, 1]]), "springs: spring 0 joins"),
    (dict(x=[[0, 0], [np.nan, 0]]), "x: contains 1 non-finite"),
    (dict(stiffness=-1.0), "stiffness"),
    (dict(mass=[1.0]), "mass: expected a scalar or shape"),
    (dict(mass=0.0), "mass: expected values > 0"),
    (dict(fixed=[7]), "fixed: index 7"),
    (dict(gravity=(0, 0, 1)), "gravity: expected 2 components"),
])
def test_bad_input(kwargs, match):
    args = dict(x=[[0.0, 0.0], [1.0, 0.0]], springs=[[0, 1]], stiffness=1.0)
    args.update(kwargs)
    x, springs = args.pop("x"), args.pop("springs")
    with pytest.raises(ValueError, match=match):
        km.massspring.System(x, springs, **args)


def test_bad_step_arguments():
    sys = oscillator()
    with pytest.raises(ValueError, match="dt"):
        sys.step(-1.0)
    with pytest.raises(ValueError, match="integrator"):
        sys.step(0.1, "rk4")
    with pytest.raises(ValueError, match="linear_solver"):
        sys.step(0.1, linear_solver="lu")


def test_default_lagged_factor_agrees_with_direct():
    # The default solves A v' = rhs, A = M - h^2 K, by PCG to cg_tol with a lagged CHOLMOD
    # factor; from the same state it differs from the direct solve by at most
    # |A^-1| cg_tol |rhs| <= cg_tol |rhs| / m_min while every spring is stretched (then -K is
    # positive semidefinite and A >= M). A cloth pre-stretched by 10% and held at its edges
    # sags under gravity and keeps them stretched; the test checks that precondition every step.
    n, cg_tol, dt, m = 12, 1e-8, 1 / 30, 1.0 / 144
    x, springs = km.massspring.cloth(n, n, 1.0)
    rest = 0.9 * np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    edge = np.flatnonzero((x[:, :2].min(axis=1) < 1e-12) | (x[:, :2].max(axis=1) > 1 - 1e-12))
    make = lambda: km.massspring.System(x, springs, stiffness=1e4, mass=m, rest_length=rest,  # noqa: E731
                                        fixed=edge, gravity=(0, 0, -9.81))
    a, b = make(), make()
    factorizations = 0
    for k in range(10):
        b.x[:], b.v[:] = a.x, a.v
        length = np.linalg.norm(a.x[springs[:, 1]] - a.x[springs[:, 0]], axis=1)
        assert (length >= rest).all(), f"step {k}: a spring is compressed; the bound does not apply"
        f = a.forces()
        f[edge] = 0  # fixed rows of the right-hand side are zero
        bound = cg_tol * np.linalg.norm(m * a.v + dt * f) / m
        info = a.step(dt, cg_tol=cg_tol)
        b.step(dt, linear_solver="cholmod_direct")
        diff = np.linalg.norm(a.v - b.v)
        assert diff <= bound, f"step {k}: |v_default - v_direct| = {diff:.2e} > {bound:.2e}"
        factorizations += info.factorizations
    assert factorizations <= 3 and info.cg_iterations > 0, (factorizations, info)
    c = hanging_cloth()
    d = hanging_cloth()
    for _ in range(10):
        info = c.step(dt, linear_solver="cholmod_pcg", cg_tol=1e-12)
        d.step(dt, linear_solver="cholmod_direct")
    assert not info.refactored and np.abs(c.x - d.x).max() < 1e-8


# ---------------------------------------------------------------- closed forms of the steps

@pytest.mark.parametrize("beta", [1.0, 0.5])
@pytest.mark.parametrize("dt", [0.05, 0.2])
def test_implicit_step_on_a_stretched_spring_is_its_closed_form(beta, dt):
    # One spring along x with vertex 0 fixed moves along its axis, where Hooke's force is
    # linear: [m + beta dt^2 k] v' = m v - dt k (x - L), x' = x + dt v' is a 2x2 linear map A.
    # 20 steps must equal A^20 applied to (x - L, v) to rounding, in 3D, with k, m, L not 1.
    k, m, L, a = 40.0, 0.5, 2.0, 0.1
    w2 = k / m
    sys = km.massspring.System([[0.0, 0.0, 0.0], [L + a, 0.0, 0.0]], [[0, 1]], stiffness=k, mass=m,
                               rest_length=L, fixed=[0])
    sys.step(dt, "implicit", beta=beta, linear_solver="cholmod_direct", steps=20)
    s = 1 / (1 + beta * dt * dt * w2)
    A = np.array([[1 - dt * dt * w2 * s, dt * s], [-dt * w2 * s, s]])
    expected = np.linalg.matrix_power(A, 20) @ [a, 0.0]
    got = [sys.x[1, 0] - L, sys.v[1, 0]]
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-14)
    assert np.abs(sys.x[1, 1:]).max() == 0 and np.abs(sys.v[1, 1:]).max() == 0


def test_free_fall_of_one_vertex_is_the_integrators_closed_form():
    # No springs: after n steps symplectic and implicit Euler give z = -g dt^2 n(n+1)/2 (the
    # velocity is updated first), explicit Euler -g dt^2 n(n-1)/2; all give v = -g n dt.
    g, dt, n = 9.81, 0.1, 10
    for integrator, factor in [("symplectic", n * (n + 1)), ("implicit", n * (n + 1)),
                               ("explicit", n * (n - 1))]:
        sys = km.massspring.System([[0.0, 0.0, 0.0]], np.zeros((0, 2), int), stiffness=1.0,
                                   gravity=(0, 0, -g))
        sys.step(dt, integrator, steps=n)
        assert sys.x[0, 2] == pytest.approx(-g * dt * dt * factor / 2, rel=1e-13), integrator
        assert sys.v[0, 2] == pytest.approx(-g * n * dt, rel=1e-13), integrator


@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "implicit"])
def test_free_system_conserves_linear_momentum(integrator):
    # Spring and damping forces come in equal and opposite pairs, and the implicit matrix's
    # rows of K and C sum to zero: total momentum is conserved to rounding by every integrator
    # (3D, unequal masses, damping, springs off their rest length).
    rng = np.random.default_rng(1)
    x = rng.random((6, 3))
    springs = [[i, j] for i in range(6) for j in range(i + 1, 6)]
    m = rng.random(6) + 0.5
    sys = km.massspring.System(x, springs, stiffness=50.0, mass=m, rest_length=0.3, damping=0.2)
    sys.v[:] = rng.standard_normal((6, 3))
    p0 = m @ sys.v
    sys.step(1e-3, integrator, steps=100)
    # rounding: ~100 steps x 15 force terms x 1e-16 relative, far below 1e-12
    assert np.abs(m @ sys.v - p0).max() < 1e-12 * np.abs(p0).max()


def test_damped_oscillator_converges_to_the_analytic_solution_at_first_order():
    # x(t) = a e^{-g t} (cos(w_d t) + g/w_d sin(w_d t)), g = c / 2m, w_d^2 = k/m - g^2, for a
    # spring damped along its axis; symplectic and implicit Euler are first order.
    k, m, L, a, c, t = 40.0, 0.5, 2.0, 0.1, 0.8, 1.0
    g = c / (2 * m)
    wd = math.sqrt(k / m - g * g)
    exact = a * math.exp(-g * t) * (math.cos(wd * t) + g / wd * math.sin(wd * t))
    for integrator in ("symplectic", "implicit"):
        errors, dts = [], [4e-4, 2e-4, 1e-4]
        for dt in dts:
            sys = km.massspring.System([[0.0, 0.0], [L + a, 0.0]], [[0, 1]], stiffness=k, mass=m,
                                       rest_length=L, fixed=[0], damping=c)
            sys.step(dt, integrator, steps=int(round(t / dt)), linear_solver="cholmod_direct")
            errors.append(abs(sys.x[1, 0] - L - exact))
        p = np.polyfit(np.log(dts), np.log(errors), 1)[0]
        assert abs(p - 1) < 0.1, f"{integrator}: order {p:.3f}, errors {errors}"
        assert errors[-1] < 0.01 * a, f"{integrator}: error {errors[-1]:.2e}"


@pytest.mark.parametrize("dim", [2, 3])
def test_chain_normal_mode_has_the_discrete_dispersion_frequency(dim):
    # A chain of N masses m between two fixed ends, springs k of rest length L, along a skew
    # direction: longitudinal mode j has the shape sin(j pi i / (N + 1)) and the angular
    # frequency 2 sqrt(k/m) sin(j pi / (2 (N + 1))) exactly (the lattice's dispersion; c = L
    # sqrt(k/m) for long waves). Small amplitude (1e-6 L: the nonlinearity of the springs'
    # transverse term is 1e-12) and symplectic Euler, whose frequency error is
    # (omega dt)^2 / 24 = 4e-7 at dt = T/500: the period to 1e-5.
    N, k, m, L, j = 30, 50.0, 0.02, 0.1, 3
    e = np.array([1.0, 2.0, 2.0][:dim]) / np.linalg.norm([1.0, 2.0, 2.0][:dim])
    i = np.arange(N + 2)
    x = np.outer(i * L, e)
    shape = np.sin(j * np.pi * i / (N + 1))
    x += 1e-6 * L * np.outer(shape, e)
    springs = np.c_[i[:-1], i[1:]]
    sys = km.massspring.System(x, springs, stiffness=k, mass=m, rest_length=L, fixed=[0, N + 1])
    omega = 2 * math.sqrt(k / m) * math.sin(j * math.pi / (2 * (N + 1)))
    period = 2 * math.pi / omega
    dt = period / 500
    probe = np.argmax(shape)
    u = np.empty(1300)
    for n in range(len(u)):
        sys.step(dt, "symplectic")
        u[n] = (sys.x[probe] - probe * L * e) @ e
    c = np.flatnonzero(np.sign(u[1:]) != np.sign(u[:-1]))
    crossings = dt * (c + 1 + u[c] / (u[c] - u[c + 1]))
    measured = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    assert abs(measured / period - 1) < 1e-5, (measured, period)


@pytest.mark.parametrize("d", [2, 3])
def test_implicit_step_names_the_real_cause_of_a_singular_matrix(d):
    # A NaN written into the x view was reported as "dt: ... makes the implicit matrix
    # non-finite"; a stiffness whose dt^2 k / m exceeds 1/eps (the mass term lost to rounding)
    # as "not positive definite; check for negative stiffness".
    x = np.zeros((3, d))
    x[:, 0] = [0, 1, 2]
    springs = [[0, 1], [1, 2]]
    for name, value in (("x", np.nan), ("v", np.inf)):
        s = km.massspring.System(x, springs, stiffness=1.0)
        getattr(s, name)[1, 0] = value
        with pytest.raises(ValueError, match=f"^{name}: holds 1 non-finite value\\(s\\) \\(first at vertex 1\\)"):
            s.step(0.01)
    stiff = km.massspring.System(x, springs, stiffness=1e300)
    stiff.x[2, 0] = 2.1
    with pytest.raises(ValueError, match="^stiffness, dt: dt\\^2 K / M reaches"):
        stiff.step(0.1)
    # Within float64's resolution the same system steps (and a stretched spring pulls back).
    ok = km.massspring.System(x, springs, stiffness=1e12)
    ok.x[2, 0] = 2.1
    ok.step(0.1)
    assert np.isfinite(ok.x).all() and ok.x[2, 0] < 2.1


def test_an_empty_spring_list_is_no_springs():
    # numpy makes [] float64: System(x, []) was refused as "expected integer indices".
    s = km.massspring.System(np.zeros((2, 2)), [], stiffness=1.0, gravity=(0, -9.81))
    assert s.springs.shape == (0, 2)
    s.step(0.1)
    np.testing.assert_allclose(s.x[:, 1], -9.81 * 0.1**2)


def test_fixed_and_springs_are_read_only_copies():
    # Writing into `fixed` did nothing (C++ holds its own copy): now the write is refused, and the
    # caller's arrays are neither shared nor frozen.
    x = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    springs, fixed = np.array([[0, 1], [1, 2]]), np.array([0])
    sys = km.massspring.System(x, springs, stiffness=10.0, fixed=fixed)
    for held in (sys.fixed, sys.springs):
        with pytest.raises(ValueError, match="read-only"):
            held[0] = 1
    springs[0, 0] = 2
    fixed[0] = 1
    assert sys.springs[0, 0] == 0 and sys.fixed[0] == 0
