"""km.mpm: exact properties of the MLS-MPM/APIC transfers, references (Sulsky's disks, Martin and
Moyce's dam break, granular column runout) and bad input, in 2D and 3D."""

import functools
import math

import numpy as np
import pytest

import kinema as km

MATERIALS = ("elastic", "neohookean", "snow", "sand", "water")


def _sim(d, n=32, gravity=(0.0, -9.81, 0.0), boundary="slip", **kw):
    return km.mpm.Simulation((n,) * d, 1.0 / n, gravity=gravity[:d], boundary=boundary, **kw)


def _add(sim, x, material, **kw):
    kw.setdefault("density", 1000.0)
    if material == "sand" and kw.get("friction_law", "constant") == "constant":
        kw.setdefault("friction_angle", 30.0)
    return sim.add_particles(x, material, **kw)


# ---------------------------------------------------------------- exact properties
@pytest.mark.parametrize("d", [2, 3])
def test_free_fall_follows_symplectic_euler_to_rounding(d):
    # A stress-free block: every grid velocity is v + dt g exactly (partition of unity) and C
    # stays 0 (linear reproduction), so each particle follows symplectic Euler:
    # y_n = y_0 + g dt^2 n (n + 1) / 2 = y_0 + g t^2/2 + g t dt / 2.
    sim = _sim(d, 32)
    x0 = km.mpm.block([0.4] * d, [0.6] * d, 1 / 64)
    _add(sim, x0, "elastic")
    dt, n = 1e-3, 100
    for _ in range(n):
        sim.step(dt)
    g = -9.81
    expected = x0.copy()
    expected[:, 1] += g * dt * dt * n * (n + 1) / 2
    err = np.abs(sim.x - expected).max()
    assert err < 1e-13, f"free fall: max |x - x_exact| = {err:.3g} (bound 1e-13 m)"
    assert np.abs(sim.v[:, 1] - g * dt * n).max() < 1e-13
    assert np.abs(sim.C).max() < 1e-10, np.abs(sim.C).max()
    assert np.abs(sim.F - np.eye(d)).max() < 1e-12


def _random_body(d, material, seed=1):
    rng = np.random.default_rng(seed)
    sim = _sim(d, 32, gravity=[0.0] * d)
    x = km.mpm.sphere([0.5] * d, 0.15, 1 / 64)
    _add(sim, x, material, velocity=rng.normal(0, 0.3, x.shape), youngs_modulus=1e4)
    sim.C[...] = rng.normal(0, 0.5, sim.C.shape)
    if material != "water":
        sim.F[...] = np.eye(d) + rng.normal(0, 0.02, sim.F.shape)
    return sim


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("material", MATERIALS)
def test_transfers_conserve_momentum_and_mass(d, material):
    # P2G and G2P conserve linear momentum (Jiang et al. 2015) and the MLS force is a sum of
    # pairs sum_i w (x_i - x_p) = 0, so without gravity and walls the total stays to rounding.
    sim = _random_body(d, material)
    p0, m0 = sim.momentum(), sim.mass.sum()
    scale = np.abs(sim.mass[:, None] * sim.v).sum()
    for _ in range(5):
        sim.step(2e-4)
    err = np.abs(sim.momentum() - p0).max()
    assert err < 1e-13 * scale, f"{material} {d}D: momentum changed by {err:.3g} (scale {scale:.3g})"
    assert sim.mass.sum() == m0


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("material", ["elastic", "neohookean"])
def test_spinning_disk_conserves_angular_momentum(d, material):
    # APIC with a symmetric Kirchhoff stress conserves angular momentum exactly (Jiang et al.
    # 2015, Sec. 5.3): the disk spins (and stretches) with L constant to rounding.
    n = 32 if d == 2 else 16
    sim = _sim(d, n, gravity=[0.0] * d)
    c = np.full(d, 0.5)
    x = km.mpm.sphere(c, 0.2, 0.5 / n)
    r = x - c
    omega = 3.0
    v = np.zeros_like(x)
    v[:, 0], v[:, 1] = -omega * r[:, 1], omega * r[:, 0]
    _add(sim, x, material, velocity=v, youngs_modulus=2e4)
    L0 = sim.angular_momentum()
    for _ in range(200):
        sim.step(5e-4)
    L = sim.angular_momentum()
    scale = np.abs(np.atleast_1d(L0)).max()
    err = np.abs(np.atleast_1d(L) - np.atleast_1d(L0)).max()
    assert err < 1e-11 * scale, f"{material} {d}D: |L - L0| = {err:.3g}, |L0| = {scale:.3g}"
    assert sim.kinetic_energy() > 0.5 * 0.5 * (sim.mass * (omega * np.linalg.norm(r[:, :2], axis=1)) ** 2).sum()


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("material", MATERIALS)
def test_rest_stays_rest(d, material):
    sim = _sim(d, 32, gravity=[0.0] * d)
    _add(sim, km.mpm.block([0.3] * d, [0.6] * d, 1 / 64), material)
    x0 = sim.x.copy()
    dt = 0.9 * sim.cfl_dt()  # CFL 0.9 (water's wave speed puts it at 6.2e-4 s)
    for _ in range(20):
        sim.step(dt)
    assert np.array_equal(sim.x, x0)
    assert not sim.v.any() and not sim.C.any()


@pytest.mark.parametrize("d", [2, 3])
def test_bitwise_determinism_for_1_and_2_threads_and_checkpoints(d):
    s = 1 / 160 if d == 2 else 1 / 48
    def run(threads, checkpoint=False):
        old = km.get_num_threads()
        km.set_num_threads(threads)
        try:
            # a fixed team: every step of the 2-thread run on 2 threads (adapt_threads may choose 1)
            sim = _sim(d, 32, boundary="separate", adapt_threads=False)
            _add(sim, km.mpm.block([0.1] * d, [0.45] + [0.6] * (d - 1), s), "water", youngs_modulus=2e5)
            _add(sim, km.mpm.block([0.55] + [0.1] * (d - 1), [0.9] * d, s), "sand")
            _add(sim, km.mpm.sphere([0.5] + [0.8] * (d - 1), 0.08, s), "snow")
            assert sim.count > 8192, "enough particles for the parallel paths"
            for k in range(12):
                if checkpoint and k == 6:
                    saved = sim.state()
                    sim2 = _sim(d, 32, boundary="separate", adapt_threads=False)
                    _add(sim2, km.mpm.block([0.1] * d, [0.45] + [0.6] * (d - 1), s), "water",
                         youngs_modulus=2e5)
                    _add(sim2, km.mpm.block([0.55] + [0.1] * (d - 1), [0.9] * d, s), "sand")
                    _add(sim2, km.mpm.sphere([0.5] + [0.8] * (d - 1), 0.08, s), "snow")
                    sim2.set_state(saved)
                    sim = sim2
                sim.step(1e-3)
            assert sim.step(1e-3).threads == threads
            return sim.state()
        finally:
            km.set_num_threads(old)

    a, b, c = run(1), run(2), run(2, checkpoint=True)
    for k in a:
        assert np.array_equal(a[k], b[k]), f"{k} differs between 1 and 2 threads"
        assert np.array_equal(a[k], c[k]), f"{k} differs after a checkpoint round trip"


# ---------------------------------------------------------------- every material, 2D and 3D
@pytest.mark.parametrize("d", [2, 3])
def test_rows_stored_in_block_order_change_no_bit_and_views_show_user_order(d):
    """The solver stores the rows sorted into grid blocks while no view is alive (after 8 quiet
    steps, then every 32); a run whose particles are read after every step stays in user
    order. Both runs, with external forces and advance() too, must agree bitwise, and the
    views after a sort must show every particle in the row it was added at."""
    s = 1 / 80 if d == 2 else 1 / 40

    def make():
        sim = _sim(d, 32, boundary="separate")
        _add(sim, km.mpm.block([0.1] * d, [0.45] + [0.5] * (d - 1), s), "water", youngs_modulus=2e5)
        _add(sim, km.mpm.sphere([0.7] + [0.5] * (d - 1), 0.15, s), "snow")
        sim.youngs_modulus[:] *= 1 + 1e-6 * np.arange(sim.count)  # a particle's E names it
        return sim

    rng = np.random.default_rng(3)
    a, b = make(), make()
    assert a.count > 1024, "enough particles for the parallel paths"
    E0, codes = a.youngs_modulus.copy(), a.material.copy()
    forces = [1e-6 * rng.standard_normal((a.count, d)) for _ in range(41)]
    for k in range(41):
        a._diff_step(1e-3, forces[k], {})
        b._diff_step(1e-3, forces[k], {})
        b.x  # a read: b's rows stay in user order
        if k == 8:
            assert a._sim.rows_in_block_order and not b._sim.rows_in_block_order
    assert a._sim.rows_in_block_order
    assert a.kinetic_energy() == b.kinetic_energy() and np.array_equal(a.momentum(), b.momentum())
    assert np.array_equal(np.atleast_1d(a.angular_momentum()), np.atleast_1d(b.angular_momentum()))
    sa, sb = a.state(), b.state()
    assert not a._sim.rows_in_block_order, "a view puts the rows back in user order"
    for k in sa:
        assert np.array_equal(sa[k], sb[k]), f"{k} differs with the rows stored in block order"
    assert np.array_equal(sa["youngs_modulus"], E0) and np.array_equal(sa["material"], codes)
    # advance() sorts as step() does; a view held across the steps keeps user order (and sees them).
    a.advance(0.02)
    x = b.x
    b.advance(0.02)
    assert a._sim.rows_in_block_order and not b._sim.rows_in_block_order
    assert np.array_equal(x, b.x) and np.array_equal(a.x, b.x)
    del x
    # Adding particles to a simulation whose rows are sorted appends them after the user rows.
    for k in range(9):
        a.step(1e-3)
    assert a._sim.rows_in_block_order
    rows = a.add_particles(km.mpm.block([0.45] * d, [0.5] * d, s), "water", density=1000.0, youngs_modulus=2e5)
    assert np.array_equal(a.youngs_modulus[: rows.start], E0) and np.all(a.youngs_modulus[rows] == 2e5)


@pytest.mark.parametrize("d", [2, 3])
def test_kept_binning_moves_crossing_particles_as_a_full_sort_would(d):
    """A step that follows the last one on an unchanged State keeps its binning into grid blocks
    and re-bins only the particles G2P saw leave their block (StepStats.rebinned); a step after a
    view was read, or with one alive, sorts all of them. Fast bodies crossing blocks (blocks
    emptied and entered), particles added mid-run, a view held across a step and written after
    it, a step that diverges and is undone: every state must be bitwise that of a run that sorts
    in full every step (a view read each step), on 1 and 2 threads."""
    s = 1 / 160 if d == 2 else 1 / 40
    up = [0.0, 1.0, 0.0][:d]
    # fast bodies up to CFL 0.93 (2D: the snow hardens; its wave speed takes cfl_dt to 4.3e-4 s)
    # and 0.78 (3D)
    dt = 4e-4 if d == 2 else 1e-3

    def run(threads, full):
        old = km.get_num_threads()
        km.set_num_threads(threads)
        try:
            sim = _sim(d, 32, boundary="separate", adapt_threads=False)
            _add(sim, km.mpm.block([0.1] * d, [0.4] + [0.35] * (d - 1), s), "water", youngs_modulus=2e5,
                 velocity=[4.0, 2.0, -3.0][:d])
            _add(sim, km.mpm.sphere([0.7] + [0.6] * (d - 1), 0.12, s), "snow", velocity=[-5.0, 1.0, 3.0][:d])
            assert sim.count > 1024, "enough particles for the parallel paths"
            stats, counts = [], []
            for k in range(70):
                if k == 30:
                    _add(sim, km.mpm.block([0.45] * d, [0.55] * d, s), "elastic", velocity=up)
                if k == 45:
                    held = sim.x  # alive during step 45, written after it
                if k == 46:
                    x = held if not full else sim.x
                    x[0] = 0.5  # particle 0 jumps to the centre: another block
                    del held, x
                if full:
                    sim.x  # a read: this step sorts in full
                stats.append(sim.step(dt))
                counts.append(sim.count)
            with pytest.warns(RuntimeWarning, match="cfl_dt"), pytest.raises(km.DivergenceError):
                sim.step(1.0)  # undone: the next step must not trust this G2P's moves
            stats.append(sim.step(dt))
            counts.append(sim.count)
            return sim.state(), [st.rebinned for st in stats], [st.particle_blocks for st in stats], counts
        finally:
            km.set_num_threads(old)

    ref, ref_rebinned, _, ref_counts = run(1, full=True)
    assert ref_rebinned == ref_counts, "a view read before every step: every step sorts in full"
    for threads in (1, 2):
        got, rebinned, blocks, counts = run(threads, full=False)
        for name in ref:
            np.testing.assert_array_equal(got[name], ref[name], err_msg=f"{name}, {threads} threads")
        # in full: the first step, after an add, after a view was taken or alive, after the undone step
        for k in (0, 30, 45, 46, 70):
            assert rebinned[k] == counts[k], (k, rebinned[k])
        kept = [k for k in range(1, 70) if k not in (30, 45, 46)]
        assert all(rebinned[k] < counts[k] for k in kept) and np.median([rebinned[k] for k in kept]) < counts[-1] / 10, rebinned
        assert sum(rebinned[k] for k in kept) > 100, "particles crossed blocks"
        assert any(blocks[k] != blocks[k - 1] for k in kept), "blocks were emptied or entered"
    assert np.isfinite(ref["x"]).all()


def test_avx2_lanes_give_the_baseline_bits_in_2d(monkeypatch):
    """2D P2G and G2P run four particles wide under AVX2 (weights, stresses, affine momentum,
    stencil sums) with the scalar code's operations in its order and no FMA, and P2G adds the
    four particles' contributions into the tile one particle at a time: every result must be
    bitwise the baseline build's (KINEMA_SIMD=baseline, read when a simulation is made). Every
    material, lanes that straddle two materials (the per-particle stress), particles with their
    own moduli, blocks whose particle count is not a multiple of four, external forces, 1 and 2
    threads, rows in user order (a view read every step) and sorted into blocks."""
    s = 1 / 128

    def run(simd, threads, read):
        if simd == "baseline":
            monkeypatch.setenv("KINEMA_SIMD", "baseline")
        else:
            monkeypatch.delenv("KINEMA_SIMD", raising=False)
        old = km.get_num_threads()
        km.set_num_threads(threads)
        try:
            sim = _sim(2, 32, boundary="separate", adapt_threads=False)
            _add(sim, km.mpm.block([0.1, 0.1], [0.3, 0.45], s), "water", youngs_modulus=2e5)
            _add(sim, km.mpm.block([0.3, 0.1], [0.5, 0.3], s), "sand")
            _add(sim, km.mpm.sphere([0.5, 0.75], 0.08, s), "snow", velocity=(0.5, -2.0))
            _add(sim, km.mpm.sphere([0.2, 0.75], 0.07, s), "elastic", velocity=(2.0, -1.0))
            _add(sim, km.mpm.sphere([0.8, 0.55], 0.07, s), "neohookean", velocity=(-2.0, 0.5))
            sim.youngs_modulus[::7] *= 1.5  # a particle's own moduli (not the material's)
            sim.poisson_ratio[np.flatnonzero(sim.material != 0)[::5]] = 0.27  # water (0) has none
            assert sim.count > 2048, "enough particles for the parallel paths"
            for k in range(40):
                f = 1e-4 * np.random.default_rng(k).standard_normal((sim.count, 2)) if k % 3 == 0 else None
                sim._diff_step(1e-3, f, {})
                if read:
                    sim.x
            if not read:
                assert sim._sim.rows_in_block_order
            return sim.state()
        finally:
            km.set_num_threads(old)

    ref = run("baseline", 1, True)
    assert np.isfinite(ref["x"]).all() and np.abs(ref["C"]).max() > 1, "the bodies deform"
    for threads, read in ((1, True), (2, False), (1, False)):
        got = run("default", threads, read)
        for k in ref:
            np.testing.assert_array_equal(got[k], ref[k], err_msg=f"{k}, {threads} threads, read={read}")


def test_adapt_threads_probes_one_thread_and_the_team_and_changes_no_bit():
    """adapt_threads times kProbe = 3 steps on one thread and 3 on the team at the start of each
    256-step cycle, then runs on the faster; a fixed team runs every step on the team. Both
    give the same bits. A bad flag is a ValueError naming it."""
    old = km.get_num_threads()
    km.set_num_threads(2)
    try:
        runs = {}
        for adapt in (True, False):
            sim = _sim(2, 32, boundary="separate", adapt_threads=adapt)
            _add(sim, km.mpm.block([0.1, 0.1], [0.6, 0.5], 1 / 160), "water", youngs_modulus=2e5)
            assert 1024 < sim.count <= 65536
            threads = [sim.step(1e-4).threads for _ in range(10)]
            runs[adapt] = sim.state()
            if adapt:
                assert threads[:6] == [1, 1, 1, 2, 2, 2] and set(threads[6:]) <= {1, 2}
            else:
                assert threads == [2] * 10
        for k in runs[True]:
            assert np.array_equal(runs[True][k], runs[False][k]), k
    finally:
        km.set_num_threads(old)
    with pytest.raises(ValueError, match="adapt_threads"):
        km.mpm.Simulation((8, 8), 0.125, adapt_threads="yes")


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("material", MATERIALS + ("sand_mu_i",))
def test_every_material_drops_settles_and_behaves(d, material):
    # "sand_mu_i": sand with the mu(I) friction law (static friction tan 30 deg, as the constant
    # law's cases), held to the same heap bounds.
    options = {}
    if material == "sand_mu_i":
        material, options = "sand", dict(SAND_MU_I)
    n = 32 if d == 2 else 16
    sim = km.mpm.Simulation((n,) * d, 1.0 / n, gravity=[0.0, -9.81, 0.0][:d], boundary="separate",
                            friction=0.5 if material == "sand" else 0.0)
    lo, hi = [0.35] + [0.05] * (d - 1), [0.65] + [0.35] * (d - 1)
    if d == 3:
        lo[2], hi[2] = 0.35, 0.65
    _add(sim, km.mpm.block(lo, hi, 0.5 / n), material, **options)
    width0 = np.ptp(sim.x[:, 0])
    sim.advance(0.4)
    x = sim.x
    assert np.isfinite(x).all() and np.isfinite(sim.F).all()
    assert (x >= 0).all() and (x <= 1).all()
    width = np.ptp(x[:, 0])
    height = np.ptp(x[:, 1])
    if material in ("elastic", "neohookean"):
        # a 1e5 Pa jelly of 0.3 m sags under its weight by rho g H^2 / E ~ 1%, no more
        assert abs(width - width0) < 0.1 * width0 and height > 0.2
        assert np.abs(np.linalg.det(sim.F) - 1).max() < 0.2
    elif material == "water":
        assert width > 2 * width0, f"water spreads: width {width:.3f} from {width0:.3f}"
    elif material == "sand":
        # A square column (aspect ratio 2 for each half) slumps to a heap about Lube et al.'s
        # 1 + 2 * 1.2 * 2 / 2 = 3.4 widths wide (their runout law, test_granular_column_runout)
        # and keeps a summit; the water of the same test covers the whole floor.
        assert width0 < width < 4.5 * width0 and height > 0.05, (width / width0, height)
    elif material == "snow":
        # the impact compacts the snow plastically (Jp < 1) and it does not bounce back
        assert sim.Jp.min() < 1 - 1e-3 and height > 0.1, (sim.Jp.min(), height)


def test_collider_stops_and_friction_holds():
    # A block sliding onto a rough sphere and a box: particles never enter them.
    sim = _sim(2, 64)
    sim.add_collider({"shape": "sphere", "center": [0.5, 0.3], "radius": 0.1}, friction=0.5)
    sim.add_collider({"shape": "box", "lower": [0.0, 0.0], "upper": [1.0, 0.1]}, boundary="sticky")
    _add(sim, km.mpm.block([0.42, 0.5], [0.58, 0.6], 1 / 128), "elastic")
    sim.advance(0.5)
    x = sim.x
    assert np.linalg.norm(x - [0.5, 0.3], axis=1).min() > 0.1 - 2 / 64
    assert x[:, 1].min() > 0.1 - 2 / 64


# ---------------------------------------------------------------- references
@functools.lru_cache(maxsize=None)
def _disks_example():
    """examples/mpm_elastic_disks.py, whose strain energy and picture these tests share."""
    from pathlib import Path

    from load_script import load_script

    return load_script(Path(__file__).resolve().parents[1] / "examples" / "mpm_elastic_disks.py")


def _strain_energy(sim):
    """Fixed-corotated energy sum V0 [mu |Sigma - I|^2 + lambda/2 (J - 1)^2] of the particles."""
    return _disks_example().strain_energy(sim)


def _disks(n):
    """Sulsky, Chen and Schreyer 1994, Sec. 5.1: two disks of radius 0.2 at (0.25, 0.25) and
    (0.75, 0.75) approach at v = +-(0.1, 0.1), E = 1000, nu = 0.3, rho = 1000, no gravity, on an
    n x n grid of the unit square; (kinetic, strain) energy every 0.1 s up to t = 3 s (before
    the rebounding disks reach the walls), and the largest |momentum| seen."""
    sim = km.mpm.Simulation((n, n), 1 / n, gravity=[0.0, 0.0])
    for c, v in (((0.25, 0.25), 0.1), ((0.75, 0.75), -0.1)):
        x = km.mpm.sphere(c, 0.2, 0.5 / n)
        sim.add_particles(x, "elastic", density=1000, youngs_modulus=1000, poisson_ratio=0.3,
                          velocity=np.full_like(x, v))
    e0 = sim.kinetic_energy()
    history, p_max = [(e0, 0.0)], 0.0
    for _ in range(30):
        sim.advance(0.1)
        history.append((sim.kinetic_energy(), _strain_energy(sim)))
        p_max = max(p_max, np.abs(sim.momentum()).max() / sim.mass.sum())
    return np.array(history), p_max, sim


def test_two_elastic_disks_collide_sulsky():
    # The disks bounce: momentum stays 0 to rounding, kinetic energy turns into strain energy
    # and back. APIC's dissipation is first order in h, so the energy lost by the end must
    # shrink at least like h (fitted order >= 0.8) from 40 to 80 cells.
    losses = []
    for n in (40, 80):
        history, p_max, sim = _disks(n)
        e0 = history[0, 0]
        ke, se = history.T
        assert p_max < 1e-15, f"{n} cells: momentum per mass {p_max:.3g}"
        assert ke.min() < 0.1 * e0, "the disks must collide (kinetic energy into strain energy)"
        assert ke[-1] > 0.8 * e0, f"{n} cells: they rebound (kinetic energy {ke[-1] / e0:.3f} e0)"
        assert sim.v[: sim.count // 2].mean(axis=0)[0] < 0, "the lower disk moves back down-left"
        losses.append(1 - (ke[-1] + se[-1]) / e0)
    order = np.log2(losses[0] / losses[1])
    assert losses[1] < 0.1 and order > 0.8, f"energy lost {losses} at 40, 80 cells: order {order:.2f}"


def test_elastic_disks_example_runs_small(tmp_path):
    # examples/mpm_elastic_disks.py (the energy-history picture of the docs) on a coarse grid up
    # to just after the collision: momentum zero to rounding, energy exchanged and mostly kept.
    results = _disks_example().main(["--out", str(tmp_path), "--cells", "32", "--duration", "2.0"])
    t, ke, se, momentum = results[32]
    assert (tmp_path / "mpm_elastic_disks.png").stat().st_size > 0
    assert momentum < 1e-15 and t[-1] == pytest.approx(2.0)
    assert se.max() > 0.5 * ke[0], "the disks squash (kinetic into strain energy)"
    assert 0.5 * ke[0] < ke[-1] + se[-1] <= ke[0] * (1 + 1e-12), "total energy is kept up to APIC's loss"


def _dam_break_front(h_cells, T_end=2.6, K=4e5):
    """2D dam break of Martin and Moyce (1952): a water column of width a and height 2a
    released against the wall x = 0; returns the front positions Z = z/a at times T."""
    a = 0.1
    n = int(round(6 * a * h_cells / a))
    h = a / h_cells
    sim = km.mpm.Simulation((n, int(3 * a / h)), h, gravity=[0.0, -9.81], boundary="slip")
    sim.add_particles(km.mpm.block([0, 0], [a, 2 * a], h / 2), "water", density=1000, youngs_modulus=K)
    scale = np.sqrt(2 * 9.81 / a)
    T, Z = [], []
    while sim.time * scale < T_end:
        sim.advance(0.05 / scale, cfl=0.5)
        T.append(sim.time * scale)
        # the front: the largest x among particles within a cell of the floor
        Z.append(sim.x[sim.x[:, 1] < 2 * h, 0].max() / a)
    return np.array(T), np.array(Z)


def test_dam_break_front_follows_martin_moyce():
    # The surge front Z(T) against the experiment (km.sph.martin_moyce()); the experiment's
    # gate opening delays the early front, so compare for T >= 1.2 where runs agree (about 10%).
    T, Z = _dam_break_front(16)
    ref = km.sph.martin_moyce()
    ref = ref[(ref[:, 0] >= 1.2) & (ref[:, 0] <= T[-1])]
    Zs = np.interp(ref[:, 0], T, Z)
    rel = np.abs(Zs - ref[:, 1]) / ref[:, 1]
    assert rel.max() < 0.15, f"front Z {Zs.round(3)} vs Martin-Moyce {ref[:, 1]} at T {ref[:, 0]}"


@pytest.mark.slow
def test_dam_break_front_converges_under_refinement():
    # The front Z(T), T in [1.2, 2.6], at 8, 16 and 32 cells per width against the 64-cell run:
    # the differences must fall at least at first order (APIC's dissipation is O(h); measured
    # 0.142, 0.062, 0.021: order 1.2-1.6). Against Martin and Moyce with one gate delay dT
    # fitted to the finest run (their gate's removal delays the measured front; fitted
    # dT = 0.27, i.e. 20 ms), the 32-cell front is within 5% (measured 2.0%).
    runs = {c: _dam_break_front(c) for c in (8, 16, 32, 64)}
    ref = km.sph.martin_moyce()
    ref = ref[(ref[:, 0] >= 1.2) & (ref[:, 0] <= 2.6)]
    Tf, Zf = runs[64]
    Tc, Zc = ref[:, 0], np.interp(ref[:, 0], Tf, Zf)
    diffs = [np.mean(np.abs(np.interp(Tc, *runs[c]) - Zc) / Zc) for c in (8, 16, 32)]
    order = -np.polyfit(np.log([8, 16, 32]), np.log(diffs), 1)[0]
    assert diffs[2] < diffs[1] < diffs[0] and order > 0.8, f"differences to 64 cells {diffs}, order {order:.2f}"
    shifts = np.linspace(0.0, 0.6, 601)
    delay = shifts[np.argmin([np.mean((np.interp(Tc - d, Tf, Zf) / ref[:, 1] - 1) ** 2) for d in shifts])]
    err32 = np.mean(np.abs(np.interp(Tc - delay, *runs[32]) - ref[:, 1]) / ref[:, 1])
    assert 0 < delay < 0.5 and err32 < 0.05, f"gate delay {delay:.3f}, 32-cell error {err32:.3f}"


def _column_runout(a, cells, **sand):
    """A 2D sand column of width L0 = 0.1 m and height a L0 against the wall x = 0 collapses on
    a rough floor (Coulomb 0.5); returns the normalised runout (L_inf - L0) / L0 of the deposit
    (its farthest particle once everything has stopped). ``sand``: the friction law's options
    of add_particles (default the constant law at 30 degrees)."""
    L0, H, h = 0.1, a * 0.1, 0.1 / cells
    nx = int(np.ceil(L0 * (2 + 4 * max(a, 1))) / h)
    sim = km.mpm.Simulation((nx, int(np.ceil(H / h)) + 4), h, gravity=[0.0, -9.81], boundary="slip", friction=0.5)
    sim.add_particles(km.mpm.block([0, 0], [L0, H], h / 2), "sand", density=1600, youngs_modulus=1e5,
                      **(sand or {"friction_angle": 30.0}))
    sim.advance(3 * np.sqrt(H / 9.81) + 0.3)  # free fall of the column, spreading, arrest
    assert np.linalg.norm(sim.v, axis=1).max() < 0.05, "the deposit has stopped"
    return (sim.x[:, 0].max() - L0) / L0


# The mu(I) sand of the column tests, no parameter fitted to them: the static friction angle of
# the constant-law tests (30 degrees, a sand's angle of repose), Jop, Forterre and Pouliquen's
# (2006) rise mu_2 - mu_s = tan 32.76 - tan 20.9 deg and I0 = 0.279, 1 mm quartz grains. The
# runouts hardly depend on the grain size (measured: a = 4, 16 cells: +17%, +11%, +4% for
# d = 0.5, 1, 2 mm; a = 0.5, 32 cells: +4%, -1%, -9%).
MU_S = math.tan(math.radians(30.0))
SAND_MU_I = dict(friction_law="mu_i", mu_s=MU_S,
                 mu_2=MU_S + math.tan(math.radians(32.76)) - math.tan(math.radians(20.9)),
                 I0=0.279, grain_diameter=1e-3, grain_density=2650.0)


@pytest.mark.parametrize("a, cells", [(0.5, 32), (4.0, 8), pytest.param(4.0, 16, marks=pytest.mark.slow)])
def test_granular_column_runout_mu_i(a, cells):
    # Lube, Huppert, Sparks and Freundt 2005 (Phys. Rev. E 72, 041301, two-dimensional
    # columns): (L_inf - L0) / L0 = 1.2 a for a below about 1.8 and 1.9 a^(2/3) above about 2.8,
    # the regimes Lajeunesse, Monnier and Homsy 2005 (Phys. Fluids 17, 103302) also find in 2D
    # channels. Tolerance 20%: the experiments' prefactors vary by that much with the material
    # and channel (Balmforth and Kerswell 2005), more than the discretisation moves these runs
    # (a = 0.5: -1% at 32 cells per width, +7% at 64; a = 4: -1% at 8, +11% at 16).
    # Measured with this law: a = 0.5 -1% (32 cells), a = 2 +14% against 1.2 a (16), a = 4 +11%
    # (16), a = 8 +6% (8 cells).
    runout = _column_runout(a, cells, **SAND_MU_I)
    ref = 1.2 * a if a < 2 else 1.9 * a ** (2 / 3)
    assert abs(runout - ref) < 0.2 * ref, f"a = {a}: runout {runout:.3f} vs Lube et al. {ref:.3f}"


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="the constant-friction law (Drucker-Prager, phi = 30 deg) runs tall "
                   "columns out too far: a = 4 +46% at 8 cells per width, +81% at 16 (and a = 0.5 +14% at 16, "
                   "+33% at 32): a rate-independent friction does not match Lube et al.; the mu(I) law does "
                   "(test_granular_column_runout_mu_i)")
@pytest.mark.parametrize("a, cells", [(4.0, 8), (0.5, 32)])
def test_granular_column_runout_constant_friction(a, cells):
    # Why it fails (measured with _column_runout, phi = 30 deg, floor friction 0.5): the excess
    # over the experiments grows with the aspect ratio (a = 0.5: +14%, 2: +41%, 4: +46%, 8:
    # +63% at 8-16 cells) and with refinement, so a finer grid does not close it; a larger
    # friction angle trades one ratio for the other (phi = 40 deg: a = 4 +15% at 16 cells but
    # a = 0.5 -23%). With the same static friction, mu(I)'s rate dependence (Jop, Forterre and
    # Pouliquen 2006; the MPM of Dunatunga and Kamrin 2015) stiffens the fast, thin, weakly
    # confined front (I large where the pressure is small), and the runouts stop growing with
    # refinement (a = 4 with mu_2 = mu_s: +8% / +30% at 8 / 16 cells; with mu(I): -1% / +11%).
    runout = _column_runout(a, cells)
    ref = 1.2 * a if a < 2 else 1.9 * a ** (2 / 3)
    assert abs(runout - ref) < 0.2 * ref, runout


def test_mu_i_options_are_checked():
    sim = km.mpm.Simulation((16, 16), 1 / 16)
    x = km.mpm.block([0.2, 0.2], [0.4, 0.4], 1 / 32)
    with pytest.raises(ValueError, match="friction_law"):
        sim.add_particles(x, "sand", density=1600, friction_law="mohr")
    with pytest.raises(ValueError, match="friction_law"):
        sim.add_particles(x, "water", density=1000, friction_law="mu_i")
    with pytest.raises(ValueError, match="friction_law"):
        sim.add_particles(x, "sand", density=1600, friction_angle=30.0, mu_s=0.5)
    with pytest.raises(ValueError, match="friction_angle"):
        sim.add_particles(x, "sand", density=1600, friction_law="mu_i", friction_angle=30.0)
    with pytest.raises(ValueError, match="mu_2"):
        sim.add_particles(x, "sand", density=1600, friction_law="mu_i", mu_s=0.6, mu_2=0.5)
    for key in ("mu_s", "I0", "grain_diameter", "grain_density"):
        with pytest.raises(ValueError, match=key):
            sim.add_particles(x, "sand", density=1600, friction_law="mu_i", **{key: -1.0})
    assert sim.count == 0
    sim.add_particles(x, "sand", density=1600, friction_law="mu_i")
    m = sim.materials[0]
    assert m.friction_law == "mu_i" and m.mu_s == pytest.approx(km.mpm.MU_I_GLASS_BEADS["mu_s"])
    assert m.friction_angle == pytest.approx(20.9)


# ---------------------------------------------------------------- bad input and blow-up
def test_bad_input_raises_value_errors_naming_the_argument():
    with pytest.raises(ValueError, match="shape"):
        km.mpm.Simulation((8,), 0.1)
    with pytest.raises(ValueError, match="h"):
        km.mpm.Simulation((8, 8), -1.0)
    with pytest.raises(ValueError, match="boundary"):
        km.mpm.Simulation((8, 8), 0.1, boundary="glue")
    with pytest.raises(ValueError, match="gravity"):
        km.mpm.Simulation((8, 8), 0.1, gravity=[0, 0, 0])
    sim = km.mpm.Simulation((16, 16), 1 / 16)
    x = km.mpm.block([0.2, 0.2], [0.4, 0.4], 1 / 32)
    with pytest.raises(ValueError, match="material"):
        sim.add_particles(x, "jelly", density=1000)
    with pytest.raises(ValueError, match="friction_angle"):
        sim.add_particles(x, "sand", density=1000)
    with pytest.raises(ValueError, match="density"):
        sim.add_particles(x, "water", density=0)
    with pytest.raises(ValueError, match="poisson_ratio"):
        sim.add_particles(x, "elastic", density=1000, poisson_ratio=0.5)
    with pytest.raises(ValueError, match="positions"):
        sim.add_particles(x + 2, "elastic", density=1000)
    with pytest.raises(ValueError, match="positions"):
        sim.add_particles(np.zeros((3, 3)), "elastic", density=1000)
    with pytest.raises(ValueError, match="velocity"):
        sim.add_particles(x, "elastic", density=1000, velocity=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="region"):
        sim.add_collider({"shape": "cone"})
    with pytest.raises(ValueError, match="radius"):
        sim.add_collider({"shape": "sphere", "center": [0.5, 0.5], "radius": -1})
    sim.add_particles(x, "elastic", density=1000)
    with pytest.raises(ValueError, match="dt"):
        sim.step(0.0)
    with pytest.raises(ValueError, match="cfl"):
        sim.stable_dt(-1)
    sim.x[0] = [5.0, 5.0]  # written through the view: caught where the step reads it
    with pytest.raises(ValueError, match="x: particle 0"):
        sim.step(1e-3)
    sim.x[0] = [0.3, 0.3]
    sim.material[0] = 7
    with pytest.raises(ValueError, match="material"):
        sim.step(1e-3)


@pytest.mark.parametrize("d", [2, 3])
def test_too_large_step_raises_divergence_not_nan(d):
    sim = _sim(d, 16)
    _add(sim, km.mpm.block([0.3] * d, [0.6] * d, 1 / 32), "elastic", youngs_modulus=1e7,
         velocity=np.array([3.0] + [0.0] * (d - 1)))
    dt = 50 * sim.stable_dt()
    with pytest.warns(RuntimeWarning, match="cfl_dt"), pytest.raises(km.DivergenceError, match="stable_dt"):
        for _ in range(200):
            before = sim.state()
            sim.step(dt)
    # The failed step left the state bitwise as it was (G2P restores what it overwrote).
    after = sim.state()
    for name, value in before.items():
        assert np.array_equal(np.asarray(after[name]), np.asarray(value)), name
    assert np.isfinite(sim.x).all()


def test_views_are_zero_copy_and_state_roundtrips():
    sim = _sim(2, 16)
    rows = _add(sim, km.mpm.block([0.2, 0.2], [0.4, 0.4], 1 / 32), "elastic")
    assert rows == slice(0, 36)
    sim.v[:, 0] = 1.0
    assert sim.momentum()[0] == pytest.approx(sim.mass.sum())
    rows2 = _add(sim, km.mpm.block([0.6, 0.2], [0.8, 0.4], 1 / 32), "water")
    assert rows2 == slice(36, 72) and sim.count == 72
    assert (sim.v[rows, 0] == 1.0).all() and (sim.material[rows2] == 1).all()
    s = sim.state()
    sim.step(1e-3)
    sim.set_state(s)
    assert np.array_equal(sim.x, s["x"]) and sim.time == 0.0
    assert sim.parameters == ("youngs_modulus", "poisson_ratio")
    with pytest.raises(ValueError, match="state"):
        sim.set_state({k: v[:3] if np.ndim(v) else v for k, v in s.items()})


def test_scene_mesh_filling_matches_the_shape():
    # The scene adapter's `mesh` object: lattice points inside a closed surface (winding number
    # in 3D, crossing number in 2D) are exactly those inside the box the surface bounds.
    from kinema.scenes.adapters.mpm import inside_mesh
    from kinema.scenes.preview import boundary_faces

    rng = np.random.default_rng(2)
    v, tets = km.fem.box_mesh([0.2, 0.3, 0.1], [0.7, 0.6, 0.5], 3)
    faces = boundary_faces(tets)
    p = rng.random((2000, 3))
    box = np.all((p > [0.2, 0.3, 0.1]) & (p < [0.7, 0.6, 0.5]), axis=1)
    assert np.array_equal(inside_mesh(p, v, faces), box)
    square = np.array([[0.2, 0.3], [0.7, 0.3], [0.7, 0.6], [0.2, 0.6]])
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    q = rng.random((2000, 2))
    assert np.array_equal(inside_mesh(q, square, edges),
                          np.all((q > [0.2, 0.3]) & (q < [0.7, 0.6]), axis=1))


@pytest.mark.slow
def test_cantilever_small_deflection_matches_fem():
    # A plane-strain beam (0.8 m x 0.1 m, clamped on its first 0.1 m) sags under gravity by
    # ~4% of its span. km.fem's static solution on a fine mesh (within 0.1% of Euler-Bernoulli
    # here) is the reference; the MPM run is damped to rest by scaling v and C each step
    # through the state views. With 8 cells through the thickness MPM's first-order error is of
    # order h / T = 0.125 at most; measured 4.4% too flexible. Bound: 10%.
    L, T, clamp, y0 = 0.8, 0.1, 0.1, 0.25
    E, nu, rho, g = 1e7, 0.3, 1000.0, 9.81
    v, tri = km.fem.rectangle_mesh([0, y0], [L, y0 + T], (128, 16))
    body = km.fem.Body(v, tri, model="corotated", youngs_modulus=E, poisson_ratio=nu, density=rho,
                       fixed=np.flatnonzero(v[:, 0] <= clamp + 1e-9), gravity=[0, -g])
    body.solve_static()
    end = np.isclose(v[:, 0], L)
    fem_tip = (body.x[end, 1] - v[end, 1]).mean()
    h = 1 / 80
    sim = km.mpm.Simulation((80, 48), h, gravity=[0, -g])
    sim.add_collider({"shape": "box", "lower": [-1, 0], "upper": [clamp + 1e-9, 0.6]}, boundary="sticky")
    x = km.mpm.block([0, y0], [L, y0 + T], h / 2)
    sim.add_particles(x, "elastic", density=rho, youngs_modulus=E, poisson_ratio=nu)
    tip = x[:, 0] > L - h / 2
    dt = sim.stable_dt(0.5)
    for _ in range(int(1.5 / dt)):
        sim.step(dt)
        sim.v[...] *= 0.999
        sim.C[...] *= 0.999
    mpm_tip = (sim.x[tip, 1] - x[tip, 1]).mean()
    assert abs(mpm_tip - fem_tip) < 0.1 * abs(fem_tip), f"tip deflection MPM {mpm_tip:.5f} vs FEM {fem_tip:.5f} m"


@pytest.mark.parametrize("d", [2, 3])
def test_bad_values_written_through_views_are_named(d):
    # A value written through a view is checked where the step reads it, and the error names
    # the array: mass and volume <= 0 used to run silently (a negative grid mass), the
    # material, modulus and ratio were all reported as "x: ... outside the domain", and a NaN
    # in F or v as a blow-up ("use a dt below stable_dt()").
    def sim():
        s = km.mpm.Simulation((16,) * d, 1 / 16)
        s.add_particles(km.mpm.block([0.4] * d, [0.6] * d, 1 / 32), "elastic", density=1e3,
                        youngs_modulus=1e4, poisson_ratio=0.3)
        s.step(1e-4)
        return s

    cases = [("mass", 0.0), ("mass", -1.0), ("volume", np.nan), ("youngs_modulus", -1.0),
             ("poisson_ratio", 0.5), ("material", 7), ("x", np.nan), ("F", np.nan), ("v", np.inf),
             ("C", np.nan)]
    for name, value in cases:
        s = sim()
        before = s.state()
        view = getattr(s, name)
        view[3] = value
        del view
        with pytest.raises(ValueError, match=f"^{name}: particle 3 "):
            s.step(1e-4)
        # the State is left as it was (the bad value included)
        after = s.state()
        for key in ("x", "F"):
            if key != name:
                np.testing.assert_array_equal(after[key], before[key])


@pytest.mark.parametrize("h", [1e-160, 1e-300, 1e120])
def test_spacing_beyond_float64_is_refused(h):
    # 1/h^2 (the APIC inertia) or h^3 overflowed into a DivergenceError blaming dt.
    with pytest.raises(ValueError, match="^h: "):
        km.mpm.Simulation((16, 16, 16), h)
