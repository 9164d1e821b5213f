"""km.vortex: the vortex-particle method on km.fmm conserves circulation and linear impulse,
matches the analytic rotation of a vortex pair, and is second order (RK4: fourth) in time."""

import numpy as np
import pytest

import kinema as km
from kinema.vortex import VortexParticles, merging_patches


def test_vortex_pair_rotates_at_the_analytic_rate():
    # Two point vortices Gamma a distance d apart turn at omega = 2 Gamma / (2 pi d^2)... for
    # equal circulations: omega = Gamma_total / (2 pi d^2) = 2 Gamma / (2 pi d^2).
    gamma, d = 1.0, 1.0
    sim = VortexParticles([[-d / 2, 0], [d / 2, 0]], [gamma, gamma], core=1e-3)
    omega = 2 * gamma / (2 * np.pi * d**2)
    t_end = 1.0
    for _ in range(50):
        sim.step(t_end / 50)
    angle = np.arctan2(sim.x[1, 1], sim.x[1, 0])
    assert angle == pytest.approx(omega * t_end, rel=1e-8), f"angle {angle}, expected {omega * t_end}"


def test_time_integration_order():
    x, g, core = merging_patches(60)
    errors = []
    ref = VortexParticles(x, g, core, eps=1e-13)
    for _ in range(32):
        ref.step(1.0 / 32)
    for steps in (2, 4, 8):
        sim = VortexParticles(x, g, core, eps=1e-13)
        for _ in range(steps):
            sim.step(1.0 / steps)
        errors.append(np.abs(sim.x - ref.x).max())
    order = np.polyfit(np.log([2, 4, 8]), np.log(errors), 1)[0]
    assert order < -2.0, f"observed order {-order:.2f} (errors {errors}), expected >= 2 (RK4)"


@pytest.mark.parametrize("n, steps", [(400, 8), pytest.param(5000, 60, marks=pytest.mark.slow)])
def test_merger_conserves_circulation_and_linear_impulse(n, steps):
    x, g, core = merging_patches(n)
    sim = VortexParticles(x, g, core, eps=1e-10)
    c0, i0 = sim.total_circulation(), sim.linear_impulse()
    x_start = sim.x.copy()
    for _ in range(steps):
        sim.step(0.25)
    assert np.abs(sim.x - x_start).max() > 0.05, "the patches should have moved"
    assert sim.total_circulation() == c0
    drift = np.linalg.norm(sim.linear_impulse() - i0)
    scale = np.abs(g).sum() * np.abs(x).max()
    assert drift < 1e-8 * scale, f"linear impulse drift {drift:.3e}, bound {1e-8 * scale:.3e}"


def test_bad_input():
    with pytest.raises(ValueError, match="x"):
        VortexParticles(np.zeros((3, 3)), np.ones(3), 0.1)
    with pytest.raises(ValueError, match="circulation"):
        VortexParticles(np.zeros((3, 2)), np.ones(2), 0.1)
    with pytest.raises(ValueError, match="core"):
        VortexParticles(np.zeros((3, 2)), np.ones(3), 0.0)
    with pytest.raises(ValueError, match="dt"):
        VortexParticles(np.random.rand(3, 2), np.ones(3), 0.1).step(-1.0)


def test_example_runs(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "examples" / "vortex_merger.py"
    spec = importlib.util.spec_from_file_location("vortex_merger", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--out", str(tmp_path), "--particles", "200", "--steps", "4", "--every", "2"])
    assert len(list((tmp_path / "frames").glob("*.png"))) == 3


def test_resume_from_state_is_bitwise_and_steps_report_stats():
    rng = np.random.default_rng(4)
    x = rng.random((300, 2))
    gamma = rng.uniform(-1, 1, 300)
    a = km.vortex.VortexParticles(x, gamma, 0.05, eps=1e-8)
    b = km.vortex.VortexParticles(x, gamma, 0.05, eps=1e-8)
    stats = a.step(0.01)
    assert isinstance(stats, km._core.StepStats)
    assert (stats.time, stats.dt, a.steps) == (pytest.approx(0.01), 0.01, 1) and stats.seconds >= 0
    saved = a.state()
    a.step(0.01)
    a.step(0.01)
    b.set_state(saved)
    b.step(0.01)
    b.step(0.01)
    assert np.array_equal(a.x, b.x) and a.time == b.time and a.steps == b.steps == 3
    assert a.parameters == ("circulation", "core")
    with pytest.raises(ValueError, match="state"):
        b.set_state({"x": np.zeros((3, 2)), "time": 0.0, "steps": 0})


def test_velocity_at_points_is_the_lamb_oseen_field_and_the_regularised_sum():
    # One vortex of circulation Gamma and core delta induces the Lamb-Oseen azimuthal speed
    # Gamma / (2 pi r) (1 - exp(-r^2/delta^2)) at any point, inside the core as beyond it.
    G, core = 2.0, 0.3
    sim = VortexParticles([[0.2, 0.1], [5.0, 5.0]], [G, 0.0], core)
    r = np.array([0.05, 0.3, 1.0, 5.0])
    u = sim.velocity(np.c_[0.2 + r, np.full(4, 0.1)])
    np.testing.assert_allclose(u[:, 1], G / (2 * np.pi * r) * (1 - np.exp(-r**2 / core**2)), rtol=1e-12)
    np.testing.assert_allclose(u[:, 0], 0.0, atol=1e-15)
    # Many vortices: the FMM and the core correction at 50 points against the direct sum;
    # at the particles' own positions the same as velocity() (own term left out).
    x, gamma, delta = merging_patches(500)
    sim = VortexParticles(x, gamma, delta)
    p = np.random.default_rng(0).uniform(-1, 1, (50, 2))
    d = p[:, None, :] - x[None]
    r2 = (d**2).sum(axis=-1)
    k = (1 - np.exp(-r2 / delta**2)) / (2 * np.pi * r2)
    direct = np.stack([-(k * d[..., 1]) @ gamma, (k * d[..., 0]) @ gamma], axis=1)
    assert np.abs(sim.velocity(p) - direct).max() < 1e-9 * np.abs(direct).max()  # FMM eps 1e-10
    np.testing.assert_allclose(sim.velocity(x), sim.velocity(), rtol=0, atol=1e-13)
    for bad in (np.zeros((3, 3)), np.full((2, 2), 1e200)):
        with pytest.raises(ValueError, match="points"):
            sim.velocity(bad)


def test_first_step_does_not_import_scipy_spatial():
    # scipy.spatial costs ~0.5 s to import (it pulls in scipy.special and qhull); the core
    # correction's pair search is the C++ cell grid, so a step must not load it.
    import subprocess
    import sys

    code = ("import sys, kinema as km\n"
            "x, g, c = km.vortex.merging_patches(200)\n"
            "km.vortex.VortexParticles(x, g, c).step(0.01)\n"
            "print('scipy.spatial' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
