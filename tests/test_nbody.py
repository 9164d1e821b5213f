"""km.nbody: a Kepler orbit's period and the leapfrog's bounded energy error and second order,
a Plummer sphere staying in virial equilibrium, momentum conservation to the FMM's eps,
softened forces against the exact softened sum, exact resume from state(), bad input and
blow-ups."""

import numpy as np
import pytest

import kinema as km
from resume import assert_resumes_bitwise


def kepler(e=0.5, a=1.0, G=1.0, m=(1.0, 1e-3)):
    """Two bodies at pericentre of an orbit of eccentricity e, semi-major axis a."""
    M = m[0] + m[1]
    rp = a * (1 - e)
    vp = np.sqrt(G * M * (1 + e) / rp)
    x = np.array([[-m[1] / M * rp, 0, 0], [m[0] / M * rp, 0, 0]])
    v = np.array([[0, -m[1] / M * vp, 0], [0, m[0] / M * vp, 0]])
    return x, v, np.array(m)


def test_kepler_period_and_bounded_energy_error():
    G, a = 1.0, 1.0
    x, v, m = kepler(e=0.5, a=a, G=G)
    period = 2 * np.pi * np.sqrt(a**3 / (G * m.sum()))
    s = km.nbody.System(x, v, m, G=G)
    e0 = s.energy()
    dt = period / 1000
    energies = []
    for _ in range(3):  # three orbits
        s.advance(period, dt, callback=lambda sy: energies.append(sy.energy()) if sy.steps % 5 == 0 else None)
    # back at pericentre after each period: the separation returns to a (1 - e)
    r = np.linalg.norm(s.x[1] - s.x[0])
    assert r == pytest.approx(a * 0.5, rel=2e-4), f"separation after 3 periods {r}"
    drift = np.abs(np.array(energies) / e0 - 1)
    # leapfrog: the error oscillates with the orbit and does not grow from orbit to orbit
    n = len(drift) // 3
    assert drift.max() < 1e-3
    assert drift[2 * n:].max() < 1.2 * drift[:n].max(), "energy error grows"


def test_leapfrog_is_second_order():
    x, v, m = kepler(e=0.3)
    errors = []
    ref = km.nbody.System(x, v, m)
    ref.advance(1.0, 0.0025)  # its own error is 1/16 of the finest run's
    for dt in (0.04, 0.02, 0.01):
        s = km.nbody.System(x, v, m)
        s.advance(1.0, dt)
        errors.append(np.abs(s.x - ref.x).max())
    slope = np.polyfit(np.log([0.04, 0.02, 0.01]), np.log(errors), 1)[0]
    assert abs(slope - 2) < 0.2, f"convergence order {slope:.2f}"


def test_plummer_sphere_stays_in_virial_equilibrium():
    x, v, m = km.nbody.plummer(1000, seed=1)
    s = km.nbody.System(x, v, m, softening=0.02)
    # finite-N sampling noise of 2K/|W| is ~ 2/sqrt(N) ~ 0.06
    assert s.virial_ratio() == pytest.approx(1.0, abs=0.1)
    e0 = s.energy()
    # two crossing times (t_cr = 2 sqrt(2) ~ 2.8 in units G = M = a = 1)
    ratios = []
    s.advance(5.6, 0.02, callback=lambda sy: ratios.append(sy.virial_ratio()) if sy.steps % 20 == 0 else None)
    assert np.abs(np.array(ratios) - 1).max() < 0.15, ratios
    # the half-mass radius of a Plummer sphere is 1.305 a (sampling noise ~ 4 % at N = 1000)
    assert np.median(np.linalg.norm(s.x, axis=1)) == pytest.approx(1.305, rel=0.1)
    assert abs(s.energy() / e0 - 1) < 2e-3


def test_momentum_conserved_to_fmm_eps():
    x, v, m = km.nbody.plummer(5000, seed=3)
    for eps in (1e-4, 1e-8):
        s = km.nbody.System(x, v, m, eps=eps, softening=0.0)
        a = s.accelerations()
        # sum m a = 0 exactly for the exact sum; the FMM's error is ~ eps |m a|
        net = np.linalg.norm(m @ a) / np.sum(m * np.linalg.norm(a, axis=1))
        assert net < eps, f"eps {eps:g}: net force {net:.2e}"
        p0 = s.momentum()
        s.advance(0.02, 0.01)
        # |dp| <= t * |sum m a| per step, with |sum m a| < eps sum m |a| as just checked
        assert np.linalg.norm(s.momentum() - p0) < 0.02 * eps * np.sum(m * np.linalg.norm(a, axis=1))


def test_softened_forces_against_exact_softened_sum():
    x, v, m = km.nbody.plummer(8000, seed=4)
    soft = 0.02
    s = km.nbody.System(x, v, m, softening=soft, eps=1e-8)
    a = s.accelerations()
    d = x[:300, None, :] - x[None, :, :]
    r2 = np.einsum("ijk,ijk->ij", d, d) + soft**2
    r2[np.arange(300), np.arange(300)] = np.inf
    ref = -np.einsum("ij,ijk->ik", m[None, :] / r2**1.5, d)
    err = np.linalg.norm(a[:300] - ref) / np.linalg.norm(ref)
    # far pairs (> 20 s apart) see 1/r: the relative force change there is < 3 s^2/(2 r^2)
    assert err < 1e-3, f"softened force error {err:.2e}"


def test_resume_from_state_is_bitwise():
    x, v, m = km.nbody.plummer(2000, seed=5)  # above the direct-sum size: the FMM runs
    assert_resumes_bitwise(lambda: km.nbody.System(x, v, m, softening=0.05, eps=1e-6),
                           lambda s: s.advance(0.03, 0.01), 1, 1, names=("x", "v", "time"))


def test_plummer_sampler():
    x, v, m = km.nbody.plummer(20000, seed=0, total_mass=2.0, scale=3.0, G=1.0)
    assert m.sum() == pytest.approx(2.0)
    assert np.abs(m @ x).max() < 1e-12 and np.abs(m @ v).max() < 1e-12
    assert np.median(np.linalg.norm(x, axis=1)) == pytest.approx(1.305 * 3.0, rel=0.03)


def test_views_are_the_state():
    x, v, m = km.nbody.plummer(100)
    s = km.nbody.System(x, v, m)
    s.x[0] += 1.0
    assert s.state()["x"][0, 0] == s.x[0, 0]


@pytest.mark.parametrize("kwargs, match", [
    (dict(x=np.zeros((3, 2)), v=np.zeros((3, 2)), mass=1.0), "x"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((2, 3)), mass=1.0), "v"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((3, 3)), mass=[1.0, 2.0]), "mass"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((3, 3)), mass=-1.0), "mass"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((3, 3)), mass=1.0, softening=-1), "softening"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((3, 3)), mass=1.0, G=0), "G"),
    (dict(x=np.zeros((3, 3)), v=np.zeros((3, 3)), mass=1.0, eps=2), "eps"),
    (dict(x=np.full((3, 3), np.nan), v=np.zeros((3, 3)), mass=1.0), "x"),
])
def test_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        km.nbody.System(**kwargs)


def test_bad_step_and_blow_up():
    x, v, m = kepler()
    s = km.nbody.System(x, v, m)
    with pytest.raises(ValueError, match="dt"):
        s.step(0)
    with pytest.raises(ValueError, match="dt"):
        s.advance(1.0, -1)
    # a force beyond the floating-point range is reported, not propagated as inf/NaN
    s = km.nbody.System([[0, 0, 0], [1e-8, 0, 0]], [[0, 0, 0], [0, 0, 0]], 1e300)
    with pytest.raises(km.DivergenceError, match="non-finite"):
        s.advance(1.0, 0.5)
    with pytest.raises(ValueError, match="n"):
        km.nbody.plummer(1)


def test_galaxy_collision_example_runs(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "galaxy_collision.py"
    spec = importlib.util.spec_from_file_location("galaxy_collision", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    worst = module.main(["--out", str(tmp_path), "--particles", "300", "--duration", "0.4",
                         "--dt", "0.05", "--frames", "2"])
    assert len(list((tmp_path / "frames").glob("*.png"))) == 3
    assert (tmp_path / "energy_error.png").exists()
    assert worst < 1e-2


def test_step_returns_step_stats():
    x, v, m = km.nbody.plummer(50, seed=2)
    s = km.nbody.System(x, v, m, softening=0.05)
    stats = s.step(0.01)
    assert isinstance(stats, km._core.StepStats)
    assert stats.time == s.time == pytest.approx(0.01) and stats.dt == 0.01 and stats.seconds >= 0
    assert repr(stats).startswith("StepStats(time=0.01, dt=0.01, seconds=")  # readable when printed


def test_advance_lands_on_the_end_and_absorbs_a_sliver():
    # The advance rule of every method (cpp/core/advance.h): a last step shorter than dt/10 is
    # merged into the step before it; a longer remainder is a short last step.
    x, v, m = km.nbody.plummer(20, seed=1)
    for duration, expected in ((0.305, [0.1, 0.2, 0.305]), (0.35, [0.1, 0.2, 0.3, 0.35])):
        s = km.nbody.System(x, v, m, softening=0.05)
        times = []
        s.advance(duration, 0.1, callback=lambda sy: times.append(sy.time))
        assert times == pytest.approx(expected, abs=1e-15) and s.time == duration


def test_leapfrog_is_time_reversible():
    # Kick-drift-kick is symmetric: 50 steps, velocities reversed, 50 steps more return to the
    # start to rounding (direct softened sum at N = 300, forces exact).
    x, v, m = km.nbody.plummer(300, seed=3)
    sim = km.nbody.System(x, v, m, softening=0.01)
    for _ in range(50):
        sim.step(0.01)
    sim.v[:] *= -1
    for _ in range(50):
        sim.step(0.01)
    assert np.abs(sim.x - x).max() < 1e-12 and np.abs(sim.v + v).max() < 1e-12


def test_units_scale_as_dimensional_analysis_says():
    # Lengths x10 (softening too) at fixed G, M: velocities / sqrt(10), times x 10^1.5, energy
    # / 10; G x2 with v x sqrt(2) and dt / sqrt(2), or masses x2 with G / 2: the same orbits.
    x, v, m = km.nbody.plummer(300, seed=3)

    def run(x, v, m, G=1.0, softening=0.01, dt=0.01):
        sim = km.nbody.System(x, v, m, G=G, softening=softening, eps=1e-12)
        for _ in range(30):
            sim.step(dt)
        return sim

    base = run(x, v, m)
    big = run(10 * x, v / np.sqrt(10), m, softening=0.1, dt=0.01 * 10**1.5)
    assert np.abs(big.x / 10 - base.x).max() < 1e-12
    assert big.energy() / base.energy() == pytest.approx(0.1, rel=1e-12)
    assert np.abs(run(x, v * np.sqrt(2), m, G=2.0, dt=0.01 / np.sqrt(2)).x - base.x).max() < 1e-12
    assert np.abs(run(x, v, 2 * m, G=0.5).x - base.x).max() < 1e-12
    mirror = np.diag([-1.0, 1.0, 1.0])
    assert np.abs(run(x @ mirror, v @ mirror, m).x @ mirror - base.x).max() < 1e-12


def test_coincident_particles_count_in_the_softened_energy():
    # Pairs at distance zero (which the FMM leaves out) have the softened potential
    # -G m_i m_j / s; groups of coincident particles against the brute-force pair sum.
    x = np.vstack([np.zeros((3, 3)), np.ones((2, 3)), [[5.0, 5.0, 5.0]]])
    m = np.arange(1.0, 7.0)
    G, s = 3.0, 0.5
    sim = km.nbody.System(x, np.zeros_like(x), m, G=G, softening=s)
    i, j = np.triu_indices(6, 1)
    exact = -G * np.sum(m[i] * m[j] / np.sqrt(((x[i] - x[j]) ** 2).sum(axis=1) + s * s))
    assert sim.potential_energy() == pytest.approx(exact, rel=1e-13)
    # Without softening their energy is infinite: said, not returned as a finite number.
    with pytest.raises(km.DivergenceError, match="coincide"):
        km.nbody.System(x, np.zeros_like(x), m).energy()
    # A massless particle on top of another adds nothing.
    two = km.nbody.System(np.zeros((2, 3)), np.zeros((2, 3)), [1.0, 0.0])
    assert two.energy() == 0.0
    # ... and the forces (which the C++ near field checks, so stepping says it too)
    sim = km.nbody.System(x, np.zeros_like(x), m)
    with pytest.raises(km.DivergenceError, match="accelerations: particles coincide"):
        sim.step(1e-3)
    assert np.array_equal(sim.x, x) and sim.steps == 0
    assert np.array_equal(two.accelerations(), np.zeros((2, 3)))


@pytest.mark.parametrize("d", [1e-200, 1e-120])
def test_close_but_distinct_particles_are_not_coincident(d):
    # Distinct particles d apart have energy -G m1 m2 / d however small d^2 is (it underflows
    # to 0 below 1e-162): never a silent 0; their force G m^2 / d^2 beyond double raises.
    x = np.array([[0.0, 0.0, 0.0], [0.0, d, 0.0]])
    sim = km.nbody.System(x, np.zeros_like(x), [2.0, 3.0], G=0.5)
    assert sim.potential_energy() == pytest.approx(-0.5 * 6.0 / d, rel=1e-14)
    if d > 1e-150:
        assert sim.accelerations()[0, 1] == pytest.approx(0.5 * 3.0 / d**2, rel=1e-14)
    else:
        with pytest.raises(km.DivergenceError, match="accelerations: non-finite"):
            sim.accelerations()


@pytest.mark.parametrize("mass", [1.0, np.zeros(0)])
def test_empty_system_is_valid(mass):
    # No particles: steps change nothing, every energy is 0, accelerations are (0, 3).
    s = km.nbody.System(np.zeros((0, 3)), np.zeros((0, 3)), mass, softening=0.1)
    assert s.accelerations().shape == (0, 3)
    assert s.energy() == 0.0 and s.kinetic_energy() == 0.0 and s.potential_energy() == 0.0
    assert np.array_equal(s.momentum(), np.zeros(3)) and np.array_equal(s.angular_momentum(), np.zeros(3))
    s.advance(0.3, 0.1)
    assert s.steps == 3 and s.time == pytest.approx(0.3) and s.x.shape == (0, 3)
    s.set_state(s.state())
    with pytest.raises(ValueError, match="potential energy is zero"):
        s.virial_ratio()
    with pytest.raises(ValueError, match="x"):
        km.nbody.System(np.zeros((0, 2)), np.zeros((0, 2)), 1.0)
