"""km.vortex.VortexParticles3D: the FMM velocity and stretching against the direct sum, a
ring's self-induced speed against Saffman's (1970) formula, ring radius and linear impulse
conserved while it travels, two coaxial rings leapfrogging, exact resume, bad input."""

import numpy as np
import pytest

import kinema as km


def test_fmm_rates_match_direct_sum():
    x, a = km.vortex.ring(1.0, 0.05, 1.0, 3000)
    x = x + 0.01 * np.random.default_rng(0).standard_normal(x.shape)
    sim = km.vortex.VortexParticles3D(x, a, 0.05, eps=1e-8)
    u, stretch = sim._rates(sim.x, sim.strength)
    out, _ = km.fmm._eval3d(sim.x, sim.strength, None, eps=1e-15, derivatives=2, kernel="gaussian",
                            length=0.05, direct=True)
    out *= km.vortex._INV_4PI
    u_ref = sim._curl(out)
    assert np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref) < 1e-7
    # stretching from the direct Hessians
    idx = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    H = out[:, :, 4:10][:, :, idx]
    grad_u = np.stack([H[:, 2, 1] - H[:, 1, 2], H[:, 0, 2] - H[:, 2, 0], H[:, 1, 0] - H[:, 0, 1]], axis=1)
    s_ref = np.einsum("nib,nb->ni", grad_u, sim.strength)
    assert np.linalg.norm(stretch - s_ref) / np.linalg.norm(s_ref) < 1e-6


def test_velocity_gradient_against_finite_differences():
    x, a = km.vortex.ring(1.0, 0.2, 1.0, 64)
    sim = km.vortex.VortexParticles3D(x, a, 0.2)
    p = np.array([[0.3, 0.2, 0.1], [1.1, 0.0, 0.05]])
    out = sim._psi(sim.x, sim.strength, p, 2)
    idx = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    H = out[:, :, 4:10][:, :, idx]
    grad_u = np.stack([H[:, 2, 1] - H[:, 1, 2], H[:, 0, 2] - H[:, 2, 0], H[:, 1, 0] - H[:, 0, 1]], axis=1)
    h = 1e-5
    for b in range(3):
        e = np.zeros(3)
        e[b] = h
        fd = (sim.velocity(p + e) - sim.velocity(p - e)) / (2 * h)
        assert np.abs(fd - grad_u[:, :, b]).max() < 1e-7 * np.abs(grad_u).max() + 1e-9


def test_thin_ring_speed_against_saffman():
    """A ring whose Gaussian core (exp(-r^2/delta^2)) is resolved by particles: its speed,
    measured from the motion of its vorticity centroid, against Saffman's formula
    U = Gamma/(4 pi R) (ln(8 R/delta) - 0.558), whose next correction is O((delta/R)^2 ln)."""
    R, delta, gamma = 1.0, 0.1, 1.0
    x, a, core = km.vortex.thick_ring(R, delta, gamma, 96, layers=3)
    sim = km.vortex.VortexParticles3D(x, a, core, eps=1e-6)
    w = np.linalg.norm(a, axis=1)
    z0 = w @ sim.x[:, 2] / w.sum()
    sim.advance(0.2, 0.1)
    w = np.linalg.norm(sim.strength, axis=1)
    speed = (w @ sim.x[:, 2] / w.sum() - z0) / 0.2
    expected = km.vortex.saffman_speed(R, delta, gamma)
    # Saffman's formula is the leading order in delta/R = 0.1; measured here -0.7 % (-0.6 % at
    # t = 0.6). The bound 1.5 % separates it from the unresolved (one-circle) ring, which moves
    # at its centreline velocity, 4 % slower (see test_thin_ring_centreline_speed).
    assert speed == pytest.approx(expected, rel=0.015), f"speed {speed:.4f}, Saffman {expected:.4f}"


def test_thin_ring_centreline_speed():
    """One circle of blobs: every particle moves along the axis at the same speed, converged
    in the particle count, 4 % below Saffman's speed (the centreline velocity of the core)."""
    speeds = []
    for n in (100, 200):
        x, a = km.vortex.ring(1.0, 0.1, 1.0, n)
        u = km.vortex.VortexParticles3D(x, a, 0.1).velocity()
        assert np.abs(u[:, :2]).max() < 1e-12 and np.ptp(u[:, 2]) < 1e-12
        speeds.append(u[0, 2])
    assert speeds[0] == pytest.approx(speeds[1], rel=1e-9)
    assert speeds[1] / km.vortex.saffman_speed(1.0, 0.1, 1.0) == pytest.approx(0.96, abs=0.005)


def test_ring_radius_and_impulse_conserved():
    R, core = 1.0, 0.15
    x, a = km.vortex.ring(R, core, 1.0, 64)
    sim = km.vortex.VortexParticles3D(x, a, core, eps=1e-8)
    i0 = sim.linear_impulse()
    assert i0 == pytest.approx([0, 0, np.pi * R**2], rel=1e-12)  # impulse of a ring: Gamma pi R^2
    u0 = sim.velocity()[:, 2].mean()
    sim.advance(2.0, 0.1)
    r = np.linalg.norm(sim.x[:, :2], axis=1)
    assert np.abs(r - R).max() < 1e-6
    assert np.linalg.norm(sim.linear_impulse() - i0) < 1e-6 * np.linalg.norm(i0)
    assert sim.x[:, 2].mean() == pytest.approx(2.0 * u0, rel=1e-6)


def test_two_rings_leapfrog():
    """Two coaxial rings of equal circulation: the rear one shrinks, speeds up and passes
    through the front one, which widens and slows (and then the roles swap)."""
    core = 0.1
    xa, aa = km.vortex.ring(1.0, core, 1.0, 60, center=(0, 0, 0))
    xb, ab = km.vortex.ring(1.0, core, 1.0, 60, center=(0, 0, 0.6))
    sim = km.vortex.VortexParticles3D(np.r_[xa, xb], np.r_[aa, ab], core, eps=1e-6)
    order = []
    for _ in range(12):  # passes at t ~ 1.5 and ~ 4.4 (examples/vortex_rings.py's plot)
        sim.advance(0.5, 0.1)
        za, zb = sim.x[:60, 2].mean(), sim.x[60:, 2].mean()
        order.append(za > zb)
    assert any(order), "the rear ring never passed the front one"
    first = order.index(True)
    assert not all(order[first:]), "the rings passed once but did not leapfrog back"


def test_resume_is_bitwise_and_bad_input():
    x, a = km.vortex.ring(1.0, 0.2, 1.0, 40)
    s1 = km.vortex.VortexParticles3D(x, a, 0.2)
    s1.advance(0.2, 0.1)
    st = s1.state()
    s1.advance(0.2, 0.1)
    s2 = km.vortex.VortexParticles3D(x, a, 0.2)
    s2.set_state(st)
    s2.advance(0.2, 0.1)
    assert np.array_equal(s1.x, s2.x) and np.array_equal(s1.strength, s2.strength)
    with pytest.raises(ValueError, match="strength"):
        km.vortex.VortexParticles3D(x, a[:, :2], 0.2)
    with pytest.raises(ValueError, match="core"):
        km.vortex.VortexParticles3D(x, a, 0.0)
    with pytest.raises(ValueError, match="dt"):
        s1.step(-1)
    with pytest.raises(ValueError, match="axis"):
        km.vortex.ring(1.0, 0.1, 1.0, 10, axis=(0, 0, 0))
    with pytest.raises(ValueError, match="n"):
        km.vortex.ring(1.0, 0.1, 1.0, 2)
    blow = km.vortex.VortexParticles3D(x, a * 1e300, 0.2)
    with pytest.raises(km.DivergenceError):
        blow.step(1.0)


def test_vortex_rings_example_runs(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "vortex_rings.py"
    spec = importlib.util.spec_from_file_location("vortex_rings", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--out", str(tmp_path), "--steps", "2", "--particles", "24", "--no-saffman"])
    assert len(list((tmp_path / "frames").glob("*.png"))) == 3
    assert (tmp_path / "leapfrog.png").exists()


def test_step_returns_step_stats():
    x, a = km.vortex.ring(1.0, 0.2, 1.0, 24)
    s = km.vortex.VortexParticles3D(x, a, 0.2)
    stats = s.step(0.05)
    assert isinstance(stats, km._core.StepStats)
    assert stats.time == s.time == pytest.approx(0.05) and stats.dt == 0.05 and s.steps == 1


def test_empty_particle_set_is_a_valid_system():
    # As the 2D VortexParticles: no particles is a system whose steps change nothing.
    s = km.vortex.VortexParticles3D(np.zeros((0, 3)), np.zeros((0, 3)), 0.2)
    s.advance(0.3, 0.1)
    assert s.x.shape == (0, 3) and s.strength.shape == (0, 3)
    assert s.steps == 3 and s.time == pytest.approx(0.3)
    assert s.velocity().shape == (0, 3)
    u = s.velocity(np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]))
    assert np.array_equal(u, np.zeros((2, 3)))
    assert np.array_equal(s.linear_impulse(), np.zeros(3))
    assert np.array_equal(s.total_strength(), np.zeros(3))
    st = s.state()
    s.set_state(st)
    with pytest.raises(ValueError, match="x"):
        km.vortex.VortexParticles3D(np.zeros((0, 2)), np.zeros((0, 2)), 0.2)


def test_empty_2d_particle_set_is_a_valid_system():
    s = km.vortex.VortexParticles(np.zeros((0, 2)), np.zeros(0), 0.2)
    s.advance(0.3, 0.1)
    assert s.x.shape == (0, 2) and s.steps == 3
    assert s.velocity().shape == (0, 2)
    assert np.array_equal(s.velocity(np.ones((2, 2))), np.zeros((2, 2)))
    assert s.total_circulation() == 0.0 and np.array_equal(s.linear_impulse(), np.zeros(2))
