"""Explicit schemes know their stability limits and say so: km.massspring (explicit and
symplectic Euler), km.fem (symplectic), km.diffusion (FTCS) and km.mpm (its CFL limit).

Each limit is checked three ways: a step at 0.9 of it runs silently (pytest turns warnings into
errors), a step beyond it warns or raises with the limit in the message, and the estimate
brackets the true limit 2 / omega_max, omega_max^2 the largest eigenvalue of M^-1 K (numpy's
eigenvalues on small systems)."""

import re
import warnings

import numpy as np
import pytest
import scipy.linalg

import kinema as km


def number_in(message, value):
    """Whether ``value`` appears in ``message`` as printed with 4 significant digits."""
    return f"{value:.4g}" in message


# ------------------------------------------------------------------ km.massspring

def spring_hessian(x, springs, k, fixed):
    """K = sum_s k_s (n n^T blocks) at rest (springs at their rest length), fixed dofs removed."""
    n, d = x.shape
    K = np.zeros((n * d, n * d))
    for (i, j), ks in zip(springs, k):
        u = x[j] - x[i]
        u /= np.linalg.norm(u)
        B = ks * np.outer(u, u)
        for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            K[a * d:(a + 1) * d, b * d:(b + 1) * d] += sign * B
    free = np.setdiff1d(np.arange(n), fixed)
    dofs = (free[:, None] * d + np.arange(d)).ravel()
    return K[np.ix_(dofs, dofs)], dofs


def true_limit(K, mass_per_dof):
    w2 = scipy.linalg.eigh(K, np.diag(mass_per_dof), eigvals_only=True).max()
    return 2 / np.sqrt(w2)


def spring_systems():
    rng = np.random.default_rng(3)
    out = []
    # a chain, pinned at one end, uneven masses and stiffnesses (2D)
    x = np.c_[np.arange(6.0), np.zeros(6)]
    springs = np.c_[np.arange(5), np.arange(1, 6)]
    out.append((x, springs, rng.uniform(1, 10, 5), rng.uniform(0.5, 2, 6), [0]))
    # a small cloth with shear and bending springs, two corners pinned (3D)
    x, springs = km.massspring.cloth(4, 4, 1.0)
    out.append((x, springs, rng.uniform(1e3, 1e4, len(springs)), rng.uniform(0.1, 1, len(x)), [0, 3]))
    # a random free cluster (no vertex fixed: rigid motions are zero modes) (3D)
    x = rng.normal(size=(7, 3))
    springs = np.array([(i, j) for i in range(7) for j in range(i + 1, 7) if rng.random() < 0.6])
    out.append((x, springs, rng.uniform(1, 100, len(springs)), rng.uniform(0.5, 2, 7), []))
    return out


@pytest.mark.parametrize("case", range(3))
def test_massspring_limits_bracket_the_true_limit(case):
    x, springs, k, m, fixed = spring_systems()[case]
    sys = km.massspring.System(x, springs, stiffness=k, mass=m, fixed=fixed)
    K, dofs = spring_hessian(x, springs, k, fixed)
    limit = true_limit(K, np.repeat(m, x.shape[1])[dofs])
    # Gershgorin's bound never refuses a stable step; unstable_dt never passes an unstable one.
    assert sys.explicit_dt_limit <= limit * (1 + 1e-12), (sys.explicit_dt_limit, limit)
    assert limit <= sys.unstable_dt * (1 + 1e-12), (limit, sys.unstable_dt)


def spectral_radius(h, K, C, m):
    """Symplectic Euler's amplification of (v, x) for M x'' = -K x - C v, damping explicit."""
    n = len(m)
    I = np.eye(n)
    a = I - h * C / m[:, None]
    A = np.block([[a, -h * K / m[:, None]], [h * a, I - h * h * K / m[:, None]]])
    return np.abs(np.linalg.eigvals(A)).max()


@pytest.mark.parametrize("case", [0, 1])
@pytest.mark.parametrize("damping", [0.0, 0.3, 3.0])
def test_massspring_symplectic_stable_below_limit_unstable_above_bound(case, damping):
    # The full linearised step (damping along the springs, per-spring values: C does not commute
    # with K): stable for every dt up to explicit_dt_limit, unstable above unstable_dt.
    x, springs, k, m, fixed = spring_systems()[case]
    c = damping * np.sqrt(k.mean() * m.mean()) * np.random.default_rng(1).uniform(0.5, 1.5, len(k))
    sys = km.massspring.System(x, springs, stiffness=k, mass=m, damping=c, fixed=fixed)
    K, dofs = spring_hessian(x, springs, k, fixed)
    C, _ = spring_hessian(x, springs, c, fixed)
    md = np.repeat(m, x.shape[1])[dofs]
    for h in np.linspace(0.05, 1, 12) * sys.explicit_dt_limit:
        assert spectral_radius(h, K, C, md) <= 1 + 1e-9, h / sys.explicit_dt_limit
    for h in np.array([1 + 1e-6, 1.1, 2]) * sys.unstable_dt:
        assert spectral_radius(h, K, C, md) > 1 + 1e-9, h / sys.unstable_dt
    if damping:
        assert sys.explicit_dt_limit < 2 / np.sqrt(sys._core.gershgorin_omega2)  # lowered


def test_massspring_window_with_uniform_springs_is_the_vertex_degree():
    # Uniform k and m: Gershgorin's omega^2 is 2 k deg_max / m, the free-free spring's Rayleigh
    # quotient 2 k / m: the warning window is sqrt(deg_max) wide, as explicit_dt_limit says.
    x, springs = km.massspring.cloth(5, 5, 1.0)
    sys = km.massspring.System(x, springs, stiffness=50.0, mass=0.2, fixed=[0, 4])
    degree = np.bincount(springs.ravel()).max()
    assert np.isclose(sys.unstable_dt / sys.explicit_dt_limit, np.sqrt(degree), rtol=1e-12)


def oscillator_chain():
    x = np.c_[np.arange(4.0), np.zeros(4)]
    return km.massspring.System(x, [[0, 1], [1, 2], [2, 3]], stiffness=100.0, mass=0.5, fixed=[0])


@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_massspring_below_limit_is_silent(integrator):
    sys = oscillator_chain()
    sys.x[3, 0] += 0.1
    sys.step(0.9 * sys.explicit_dt_limit, integrator, steps=20)  # a warning would fail the test
    assert np.isfinite(sys.x).all()


@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_massspring_beyond_limit_warns_once_per_call(integrator):
    sys = oscillator_chain()
    limit, bound = sys.explicit_dt_limit, sys.unstable_dt
    assert bound > 1.2 * limit  # a window to warn in
    dt = 0.5 * (limit + bound)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sys.step(dt, integrator, steps=3)
    assert [w.category for w in caught] == [RuntimeWarning]
    assert caught[0].filename == __file__  # the caller's line, not kinema's
    message = str(caught[0].message)
    assert message.startswith("dt:") and number_in(message, dt) and number_in(message, limit), message


@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_massspring_certainly_unstable_step_raises_before_stepping(integrator):
    sys = oscillator_chain()
    x0 = sys.x.copy()
    dt = 1.01 * sys.unstable_dt
    with pytest.raises(ValueError, match=re.escape(f"{sys.unstable_dt:.4g}")):
        sys.step(dt, integrator)
    assert np.array_equal(sys.x, x0) and sys.time == 0


def test_massspring_huge_stiffness_one_step_is_refused():
    # k = 1e300 with a 0.1 s symplectic step returned x ~ -1e297 without a word.
    sys = km.massspring.System([[0.0, 0.0], [1.1, 0.0]], [[0, 1]], stiffness=1e300, mass=1.0,
                               rest_length=1.0, fixed=[0])
    with pytest.raises(ValueError, match="dt: 0.1 s") as info:
        sys.step(0.1, "symplectic")
    assert number_in(str(info.value), sys.explicit_dt_limit)
    assert sys.x[1, 0] == 1.1
    sys.step(0.1, "implicit")  # the implicit step is unconditionally stable: no check
    assert abs(sys.x[1, 0] - 1.0) < 1e-12


def test_massspring_implicit_and_springless_steps_are_unchecked():
    sys = oscillator_chain()
    sys.step(100 * sys.unstable_dt, "implicit")
    free = km.massspring.System([[0.0, 0.0]], [], stiffness=1.0, gravity=(0, -9.81))
    assert free.explicit_dt_limit == free.unstable_dt == float("inf")
    free.step(10.0, "symplectic")


def chain_with(**parameters):
    """oscillator_chain's springs and masses (damped), with some parameters replaced."""
    values = dict(stiffness=100.0, mass=0.5, damping=0.2) | parameters
    x = np.c_[np.arange(4.0), np.zeros(4)]
    return km.massspring.System(x, [[0, 1], [1, 2], [2, 3]], fixed=[0], **values)


@pytest.mark.parametrize("name, value", [("stiffness", [400.0, 100.0, 900.0]), ("mass", 0.05),
                                         ("damping", 8.0), ("rest_length", [1.0, 1.5, 0.5])])
def test_massspring_limits_follow_a_parameter_set_after_construction(name, value):
    # The limits are cached in C++: a parameter set afterwards (the path km.diff and km.torch set
    # parameters through) must give the limits of a system built with it, and the checks must
    # use them: a step that was silent now warns (stiffer, lighter or more damped springs) and
    # one beyond the new unstable_dt is refused before stepping.
    sys = chain_with()
    old = sys.explicit_dt_limit, sys.unstable_dt
    sys._diff_set(name, value)
    fresh = chain_with(**{name: value})
    assert (sys.explicit_dt_limit, sys.unstable_dt) == (fresh.explicit_dt_limit, fresh.unstable_dt)
    if name == "rest_length":  # K and C at rest do not depend on L: the same limits
        assert (sys.explicit_dt_limit, sys.unstable_dt) == old
        return
    limit, bound = sys.explicit_dt_limit, sys.unstable_dt
    assert limit < 0.8 * old[0], (limit, old)
    dt = 1.05 * limit
    assert dt < min(bound, 0.9 * old[0])  # silent with the old limits, in the window of the new
    chain_with().step(dt, "symplectic", steps=2)  # (a warning would fail the test)
    with pytest.warns(RuntimeWarning, match=re.escape(f"explicit_dt_limit = {limit:.4g} s")):
        sys.step(dt, "symplectic", steps=2)
    if name == "damping":  # damping lowers the conservative limit only; the Rayleigh bound stays
        assert bound == old[1]
        return
    assert bound < 0.9 * old[0]
    x0, t0 = sys.x.copy(), sys.time
    with pytest.raises(ValueError, match=re.escape(f"{bound:.4g} s (unstable_dt)")):
        sys.step(0.5 * (bound + min(old[0], 1.1 * bound)), "explicit")
    assert np.array_equal(sys.x, x0) and sys.time == t0


def test_massspring_limits_follow_parameters_set_through_torch():
    torch = pytest.importorskip("torch")
    import kinema.torch

    sys = chain_with()
    old = sys.explicit_dt_limit
    limit = chain_with(stiffness=[400.0] * 3).explicit_dt_limit
    dt = 1.05 * limit
    assert dt < 0.9 * old  # silent with the stiffness the system was built with
    k = torch.full((3,), 400.0, dtype=torch.float64, requires_grad=True)
    with pytest.warns(RuntimeWarning, match=re.escape(f"explicit_dt_limit = {limit:.4g} s")):
        out = kinema.torch.rollout(sys, 2, dt, {"stiffness": k}, integrator="symplectic")
    assert sys.explicit_dt_limit == limit
    out["x"].sum().backward()
    assert torch.isfinite(k.grad).all()


def contact_bodies():
    """A spring chain and a triangle body above a floor (km.contact's projected steps)."""
    x = np.c_[np.arange(4.0), np.ones(4)]
    chain = km.massspring.System(x, [[0, 1], [1, 2], [2, 3]], stiffness=100.0, mass=0.5, fixed=[0],
                                 gravity=(0, -9.81))
    V, T = km.fem.rectangle_mesh((0, 0.1), (1, 0.6), (4, 2))
    body = km.fem.Body(V, T, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0, gravity=(0, -9.81))
    for sim in (chain, body):
        sim.add_collider("plane", point=(0, 0), normal=(0, 1))
    return chain, body


@pytest.mark.parametrize("case", [0, 1])
@pytest.mark.parametrize("through", ["step", "contact.step"])
def test_explicit_limit_is_checked_once_per_call_with_colliders(case, through):
    # A body with colliders takes km.contact's projected symplectic steps: the body's limits
    # hold (projection adds no stiffness), checked once per call, the warning naming the
    # caller's line; beyond unstable_dt the call is refused before any step.
    sim = contact_bodies()[case]
    step = sim.step if through == "step" else sim.contact.step
    limit, bound = sim.explicit_dt_limit, sim.unstable_dt
    step(0.9 * limit, "symplectic", steps=2)  # silent
    dt = 0.5 * (limit + bound)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        step(dt, "symplectic", steps=3)
    assert [w.category for w in caught] == [RuntimeWarning]
    assert caught[0].filename == __file__ and number_in(str(caught[0].message), limit)
    x0, t0 = sim.x.copy(), sim.time
    with pytest.raises(ValueError, match=re.escape(f"{bound:.4g} s (unstable_dt)")):
        step(1.01 * bound, "symplectic", steps=3)
    assert np.array_equal(sim.x, x0) and sim.time == t0


# ------------------------------------------------------------------ km.fem

def fem_bodies():
    V2, T2 = km.fem.rectangle_mesh((0, 0), (1, 0.5), (4, 2))
    V3, T3 = km.fem.box_mesh((0, 0, 0), (1, 0.5, 0.5), (3, 2, 2))
    rng = np.random.default_rng(5)
    V2p = V2 + rng.uniform(-0.03, 0.03, V2.shape)  # an irregular mesh, uneven moduli
    E = rng.uniform(1e5, 1e6, len(T2))
    return [
        ("triangles", km.fem.Body(V2, T2, model="linear", youngs_modulus=1e5, poisson_ratio=0.3,
                                  density=1000.0, fixed=np.flatnonzero(V2[:, 0] == 0)), 1.75),
        ("tetrahedra", km.fem.Body(V3, T3, model="neohookean", youngs_modulus=1e5, poisson_ratio=0.3,
                                   density=1000.0, fixed=np.flatnonzero(V3[:, 0] == 0)), 2.3),
        ("irregular", km.fem.Body(V2p, T2, model="stvk", youngs_modulus=E, poisson_ratio=0.45,
                                  density=500.0), None),
    ]


@pytest.mark.parametrize("case", range(3))
def test_fem_limits_bracket_the_true_limit(case):
    name, body, factor = fem_bodies()[case]
    d = body.x.shape[1]
    K = body.hessian().toarray()  # at rest: the body has not moved
    free = np.setdiff1d(np.arange(len(body.x)), body.fixed)
    dofs = (free[:, None] * d + np.arange(d)).ravel()
    limit = true_limit(K[np.ix_(dofs, dofs)], np.repeat(body.mass, d)[dofs])
    assert body.explicit_dt_limit <= limit * (1 + 1e-12), (name, body.explicit_dt_limit, limit)
    assert limit <= body.unstable_dt * (1 + 1e-12), (name, limit, body.unstable_dt)
    if factor is not None:
        # The docstring's figure (measured over rectangle_mesh / box_mesh sizes and nu in [0, 0.45]):
        # Gershgorin's omega_max^2 is at most `factor` times the true one, so a warning fires on a
        # stable step only within sqrt(factor) of the limit.
        ratio = (limit / body.explicit_dt_limit) ** 2
        assert ratio <= factor, (name, ratio)


@pytest.mark.parametrize("damping", [0.0, 50.0, 2000.0])
def test_fem_damped_limit_brackets_the_true_limit(damping):
    # The symplectic step with implicit mass damping c: v' = (v + h M^-1 f) / (1 + h c);
    # its amplification's spectral radius is <= 1 up to explicit_dt_limit and > 1 above unstable_dt.
    V, T = km.fem.rectangle_mesh((0, 0), (1, 0.5), (3, 2))
    body = km.fem.Body(V, T, model="linear", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0,
                       fixed=np.flatnonzero(V[:, 0] == 0), damping=damping)
    free = np.setdiff1d(np.arange(len(V)), body.fixed)
    dofs = (free[:, None] * 2 + np.arange(2)).ravel()
    K = body.hessian().toarray()[np.ix_(dofs, dofs)] / np.repeat(body.mass, 2)[dofs][:, None]
    I = np.eye(len(dofs))

    def radius(h):
        a = 1 / (1 + h * damping)
        A = np.block([[a * I, -a * h * K], [a * h * I, I - a * h * h * K]])
        return np.abs(np.linalg.eigvals(A)).max()
    for h in np.linspace(0.05, 1, 12) * body.explicit_dt_limit:
        assert radius(h) <= 1 + 1e-9
    for h in np.array([1 + 1e-6, 1.1, 2]) * body.unstable_dt:
        assert radius(h) > 1 + 1e-9, h / body.unstable_dt


def test_fem_below_limit_is_silent_and_beyond_warns_or_raises():
    _, body, _ = fem_bodies()[1]
    body.v[:, 2] = 0.01
    body.v[body.fixed] = 0
    limit, bound = body.explicit_dt_limit, body.unstable_dt
    body.step(0.9 * limit, "symplectic", steps=10)  # silent
    dt = 0.5 * (limit + bound)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        body.step(dt, "symplectic", steps=2)
    assert [w.category for w in caught] == [RuntimeWarning] and caught[0].filename == __file__
    assert number_in(str(caught[0].message), dt) and number_in(str(caught[0].message), limit)
    x0 = body.x.copy()
    with pytest.raises(ValueError, match=re.escape(f"{bound:.4g}")):
        body.step(1.01 * bound, "symplectic")
    assert np.array_equal(body.x, x0)
    body.step(100 * bound)  # implicit: unchecked


@pytest.mark.parametrize("name, scale", [("youngs_modulus", 16.0), ("density", 1 / 16), ("damping", None)])
def test_fem_limits_follow_a_parameter_set_after_construction(name, scale):
    # A parameter set after construction (km.diff's and km.torch's path) rebuilds the solver:
    # the limits must be those of a body built with it (unstable_dt too, which is cached), and
    # the checks must warn and refuse at them.
    def body(**values):
        V, T = km.fem.box_mesh((0, 0, 0), (1, 0.5, 0.5), (3, 2, 2))
        values = dict(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0, damping=0.0) | values
        return km.fem.Body(V, T, fixed=np.flatnonzero(V[:, 0] == 0), **values)

    b = body()
    old = b.explicit_dt_limit, b.unstable_dt  # (unstable_dt now cached)
    value = 400.0 if scale is None else scale * b._diff_get(name)
    b._diff_set(name, value)
    fresh = body(**{name: value})
    assert (b.explicit_dt_limit, b.unstable_dt) == (fresh.explicit_dt_limit, fresh.unstable_dt)
    limit, bound = b.explicit_dt_limit, b.unstable_dt
    if name == "damping":  # implicit mass damping raises the true limit only: unstable_dt grows
        assert limit == old[0] and bound > 1.5 * old[1]
        with pytest.warns(RuntimeWarning, match="explicit_dt_limit"):
            b.step(0.5 * (old[1] + min(bound, 2 * old[1])), "symplectic")  # refused before
        return
    assert limit < 0.3 * old[0] and bound < 0.3 * old[1]
    dt = 0.5 * (limit + bound)
    assert dt < old[0]  # silent with the parameters the body was built with
    with pytest.warns(RuntimeWarning, match=re.escape(f"explicit_dt_limit = {limit:.4g} s")):
        b.step(dt, "symplectic")
    x0 = b.x.copy()
    with pytest.raises(ValueError, match=re.escape(f"{bound:.4g} s (unstable_dt)")):
        b.step(1.01 * bound, "symplectic")
    assert np.array_equal(b.x, x0)


def test_fem_huge_modulus_one_step_is_refused():
    V, T = km.fem.rectangle_mesh((0, 0), (1, 1), 1)
    body = km.fem.Body(V, T, model="linear", youngs_modulus=1e250, poisson_ratio=0.3, density=1.0,
                       fixed=[0, 1])
    body.x[3, 0] += 0.1
    with pytest.raises(ValueError, match="dt: 0.1 s"):
        body.step(0.1, "symplectic")
    assert body.x[3, 0] == V[3, 0] + 0.1


# ------------------------------------------------------------------ km.diffusion (FTCS)

@pytest.mark.parametrize("d", [2, 3])
def test_ftcs_limit_is_exact_and_refused_beyond(d):
    shape, h, kappa = (8,) * d, 0.1, 2.0
    limit = km.diffusion.stable_dt(h, kappa, d)
    # The largest eigenvalue of the Neumann Laplacian is 4 d / h^2 sin^2(pi (n-1) / (2 n)) < 4 d / h^2,
    # approaching it as n grows: dt = h^2 / (2 d kappa) is the exact limit of large grids.
    lam = 4 * d / h**2 * np.sin(np.pi * 7 / 16) ** 2
    assert limit <= 2 / (kappa * lam) < 1.05 * limit
    T = np.random.default_rng(0).normal(size=shape)
    out = km.diffusion.step(T, kappa, 0.9 * limit, h, scheme="ftcs", steps=50)
    assert np.abs(out).max() <= np.abs(T).max()  # a maximum principle below the limit
    with pytest.raises(km.StabilityError, match=re.escape(f"{limit:.4g}")):
        km.diffusion.step(T, kappa, 1.5 * limit, h, scheme="ftcs")
    assert issubclass(km.StabilityError, ValueError)


# ------------------------------------------------------------------ km.mpm

def mpm_block(d):
    sim = km.mpm.Simulation((16,) * d, 1 / 16)
    g = (np.arange(8) + 0.5) / 32 + 0.3
    x = np.stack(np.meshgrid(*[g] * d, indexing="ij"), -1).reshape(-1, d)
    sim.add_particles(x, material="elastic", density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3)
    return sim


@pytest.mark.parametrize("d", [2, 3])
def test_mpm_beyond_cfl_limit_warns(d):
    sim = mpm_block(d)
    limit = sim.cfl_dt()
    c = np.sqrt(1e5 * (1 - 0.3) / ((1 + 0.3) * (1 - 0.6)) / 1000.0)  # sqrt((lambda + 2 mu) / rho)
    assert np.isclose(limit, (1 / 16) / c, rtol=1e-12)
    sim.step(0.9 * limit)  # silent
    dt = 2 * sim.cfl_dt()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            sim.step(dt)
        except km.DivergenceError:
            pass
    assert [w.category for w in caught] == [RuntimeWarning] and caught[0].filename == __file__
    assert number_in(str(caught[0].message), dt)


def test_mpm_run_beyond_the_limit_warns_once_then_as_it_grows():
    # A run at a dt just beyond cfl_dt() (Taichi's mpm128 step is at CFL 1.04 for this estimate)
    # warns at its first step, then only when the CFL number has grown 10% since; a step within
    # the limit ends the run of warnings. (A block at rest: cfl_dt() stays what it was.)
    sim = mpm_block(2)
    limit = sim.cfl_dt()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(10):
            sim.step(1.05 * limit)
        assert len(caught) == 1 and "CFL number 1.05" in str(caught[0].message)
        sim.step(1.2 * limit)  # 14% further: warned
        sim.step(1.25 * limit)  # 4% further: not
        assert [str(w.message).count("CFL number 1.2,") for w in caught] == [0, 1]
        sim.step(0.9 * limit)  # within: the run ends
        sim.step(1.05 * limit)
    assert len(caught) == 3 and sim.cfl_dt() == limit


def test_mpm_cfl_limit_is_near_the_observed_blow_up():
    # The estimate is not loose: moving water stays finite at CFL 0.9 and blows up at CFL 2
    # (measured: from CFL 1.2 on), the step's own DivergenceError reporting it.
    def run(cfl, steps=120):
        sim = km.mpm.Simulation((32, 32), 1 / 32)
        sim.add_particles(km.mpm.block([0.3, 0.3], [0.6, 0.6], 1 / 64), "water", density=1000.0,
                          youngs_modulus=1e5, velocity=[1.0, 0.0])
        for _ in range(steps):
            sim.step(cfl * sim.cfl_dt())
        return sim
    assert np.isfinite(run(0.9).kinetic_energy())
    with pytest.warns(RuntimeWarning, match="cfl_dt"), pytest.raises(km.DivergenceError):
        run(2.0)


def mpm_mixed(d):
    """Water, snow thrown at a wall (it yields: its hardening raises its wave speed) and an
    elastic disc with some particles' own moduli: every term of the signal speed."""
    s = 1 / 96 if d == 2 else 1 / 40
    sim = km.mpm.Simulation((32,) * d, 1 / 32, gravity=(0.0, -9.81, 0.0)[:d], boundary="separate")
    sim.add_particles(km.mpm.block([0.1] * d, [0.3] * d, s), "water", density=1000.0, youngs_modulus=2e5)
    sim.add_particles(km.mpm.sphere([0.82] + [0.5] * (d - 1), 0.1, s), "snow", density=400.0,
                      velocity=[6.0, -1.0, 0.5][:d])
    rows = sim.add_particles(km.mpm.sphere([0.45] * d, 0.08, s), "elastic", density=1000.0,
                             velocity=[-2.0, 1.0, 0.0][:d])
    sim.youngs_modulus[rows.start::5] *= 1.5  # (snow, 19.7 m/s unhardened, is the fastest wave)
    return sim


@pytest.mark.parametrize("d, simd", [(2, "default"), (2, "baseline"), (3, "default")])
def test_mpm_cfl_dt_measured_by_the_step_is_the_full_pass_bit_for_bit(d, simd, monkeypatch):
    # The check before each step reads what the last step measured (largest speed and snow
    # hardening in G2P; the wave speeds of the moduli kept from one pass): it must be the pass
    # over the particles a view forces, bit for bit, in 2D's AVX2 lanes and scalar code and 3D.
    if simd == "baseline":
        monkeypatch.setenv("KINEMA_SIMD", "baseline")
    a, b = mpm_mixed(d), mpm_mixed(d)
    for k in range(25):
        # after the first step, the first limit asked for passes over the particles (and keeps
        # the wave speeds); from the second on, what the step measured is read
        assert a._sim.speed_measured == (k >= 2), k
        dt = a.stable_dt(0.5)
        b.x  # a view read: b's limits come from a pass over its particles
        assert not b._sim.speed_measured
        assert (a.cfl_dt(), dt) == (b.cfl_dt(), b.stable_dt(0.5)), k
        a.step(dt)
        b.step(dt)
    snow = a.material == 1
    assert a.Jp[snow].min() < 0.999, "the snow yielded: its hardening counts"


def test_mpm_check_sees_what_is_written_after_a_step():
    # After steps with the limit read from the last one, a modulus set through km.diff's path, a
    # velocity written through a view taken after the step and one written through a view held
    # across steps are each seen by the next step's check.
    sim = mpm_block(2)
    for _ in range(3):
        sim.step(0.5 * sim.cfl_dt())
    assert sim._sim.speed_measured
    old = sim.cfl_dt()
    sim._diff_set("youngs_modulus", 100 * sim.youngs_modulus)
    assert not sim._sim.speed_measured
    limit = sim.cfl_dt()
    assert limit < 0.15 * old
    with pytest.warns(RuntimeWarning, match=re.escape(f"cfl_dt() = {limit:.4g} s")):
        sim.step(0.5 * old)
    sim = mpm_block(3)
    for _ in range(3):
        sim.step(0.5 * sim.cfl_dt())
    old = sim.cfl_dt()
    sim.v[7] = (0.0, 0.0, 5 / 16 / (0.5 * old))  # 5 cells in the step of CFL 0.5
    with pytest.warns(RuntimeWarning, match="cfl_dt"):
        sim.step(0.5 * old)
    held = sim.v
    dt = 0.4 * sim.cfl_dt()
    sim.step(dt)  # silent
    held[3] = (0.0, 0.0, 5 / 16 / dt)
    with pytest.warns(RuntimeWarning, match="cfl_dt"):
        sim.step(dt)


def test_mpm_advance_warns_for_cfl_above_one():
    sim = mpm_block(2)
    sim.advance(0.9 * sim.cfl_dt(), cfl=0.9)  # silent
    with pytest.warns(RuntimeWarning, match="cfl: 1.5 > 1"):
        sim.advance(1e-4, cfl=1.5)
