"""Thread safety: each simulation object stepped (or queried, or written) from two Python
threads at once. Every object serialises its own calls, so the result equals the same calls
made one after another; each scenario runs in a subprocess so that a crash fails the test
rather than killing pytest."""

import subprocess
import sys
import textwrap

import pytest

PRELUDE = """
import threading
import numpy as np
import kinema as km

def both(fn, n):
    errors = []
    def run():
        try:
            for _ in range(n):
                fn()
        except BaseException as exc:  # reported by the parent
            errors.append(exc)
    ts = [threading.Thread(target=run) for _ in range(2)]
    for t in ts: t.start()
    for t in ts: t.join()
    assert not errors, errors
"""

SCENARIOS = {
    # two threads step one object N times each: serialised, the state is that of 2N steps
    "massspring": """
        x, s = km.massspring.cloth(12, 12, 1.0)
        make = lambda: km.massspring.System(x, s, stiffness=1e3, mass=0.01, gravity=[0, 0, -9.8], fixed=[0, 11])
        a, b = make(), make()
        both(lambda: a.step(1e-3), 10)
        b.step(1e-3, steps=20)
        assert a.time == b.time
        np.testing.assert_array_equal(a.x, b.x)
    """,
    "fem": """
        v, e = km.fem.rectangle_mesh([0, 0], [1, 0.2], (10, 3))
        make = lambda: km.fem.Body(v, e, youngs_modulus=1e5, poisson_ratio=0.3, density=1e3,
                                   fixed=[0, 1, 2, 3], gravity=[0, -9.8])
        a, b = make(), make()
        both(lambda: a.step(1e-2), 5)
        for _ in range(10): b.step(1e-2)
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
        assert abs(a.time - b.time) < 1e-12
    """,
    "sph": """
        x = km.sph.block([0, 0], [0.2, 0.2], 0.01) + 0.005
        a = km.sph.Fluid(x, 0.01, gravity=[0, -9.8], domain=([0, 0], [0.4, 0.4]))
        stop = threading.Event()
        def query():
            while not stop.is_set():
                a.kinetic_energy(); a.density_error(); a.neighbor_pairs(); a.x.sum()
        q = threading.Thread(target=query); q.start()
        try:
            both(lambda: a.step(1e-4), 10)
        finally:
            stop.set(); q.join()
        assert abs(a.time - 20e-4) < 1e-12
    """,
    "mpm": """
        def make():
            sim = km.mpm.Simulation((16, 16), 1 / 16, gravity=[0, -9.8])
            sim.add_particles(km.mpm.block([0.3, 0.3], [0.6, 0.6], 1 / 32), "elastic", density=1e3,
                              youngs_modulus=1e4, poisson_ratio=0.3)
            return sim
        a, b = make(), make()
        both(lambda: a.step(1e-3), 10)
        for _ in range(20): b.step(1e-3)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.F, b.F)
    """,
    "nbody_vortex3d": """
        x, v, m = km.nbody.plummer(300, seed=1)
        a, b = km.nbody.System(x, v, m, softening=0.05), km.nbody.System(x, v, m, softening=0.05)
        both(lambda: a.step(1e-3), 5)
        for _ in range(10): b.step(1e-3)
        np.testing.assert_array_equal(a.x, b.x)
        xr, s = km.vortex.ring(1.0, 0.2, 1.0, 32)
        c, d = km.vortex.VortexParticles3D(xr, s, 0.2), km.vortex.VortexParticles3D(xr, s, 0.2)
        both(lambda: c.step(1e-2), 3)
        for _ in range(6): d.step(1e-2)
        np.testing.assert_array_equal(c.x, d.x)
    """,
    "grid": """
        a = km.grid.Fluid((48, 48), 1 / 48, gravity=[0, -9.8], density=True, buoyancy=(0, 1))
        b = km.grid.Fluid((48, 48), 1 / 48, gravity=[0, -9.8], density=True, buoyancy=(0, 1))
        both(lambda: a.step(1e-2), 5)
        for _ in range(10): b.step(1e-2)
        np.testing.assert_array_equal(a.u, b.u)
        assert a.steps == 10
    """,
    # one thread steps while another writes NaN into the velocity view and restores it: the
    # step may report the NaN (DivergenceError, state rolled back) but memory is never corrupted
    "grid_nan_writer": """
        a = km.grid.Fluid((64, 64), 1 / 64, gravity=[0, -9.8])
        u = a.u
        stop = threading.Event()
        def writer():
            while not stop.is_set():
                u[10:20, 10:20] = np.nan
                u[10:20, 10:20] = 0.0
        w = threading.Thread(target=writer); w.start()
        diverged = 0
        try:
            for _ in range(40):
                try:
                    a.step(1e-2)
                except km.DivergenceError:
                    diverged += 1
        finally:
            stop.set(); w.join()
        print("diverged", diverged)
    """,
    "sph_nan_writer": """
        x = km.sph.block([0, 0], [0.2, 0.2], 0.01) + 0.005
        a = km.sph.Fluid(x, 0.01, gravity=[0, -9.8], domain=([0, 0], [0.4, 0.4]))
        xv, vv = a.x, a.v
        stop = threading.Event()
        def writer():
            rng = np.random.default_rng(0)
            while not stop.is_set():
                i = rng.integers(0, len(xv), 20)
                old = xv[i].copy(); xv[i] = np.nan; vv[i] = 1e300; xv[i] = old; vv[i] = 0
        w = threading.Thread(target=writer); w.start()
        try:
            for _ in range(30):
                try:
                    a.step(1e-4)
                except (km.DivergenceError, ValueError):
                    pass
        finally:
            stop.set(); w.join()
    """,
    "render": """
        sc = km.render.Scene()
        sc.add_spheres([[0, 0, 0]], [1.0], km.render.lambertian())
        cam = km.render.Camera([0, 0, 5], [0, 0, 0], width=48, height=32)
        def grow():
            sc.add_spheres(np.random.default_rng().random((20, 3)) * 2 - 1, np.full(20, 0.1), km.render.lambertian())
        def draw():
            img = sc.render(cam, spp=2)
            assert np.isfinite(img).all()
        t = threading.Thread(target=lambda: [grow() for _ in range(30)])
        t.start()
        both(draw, 3)
        t.join()
        assert sc.sphere_count == 1 + 600
    """,
    "vortex_poisson": """
        p = km.poisson.Solver((32, 32), 1 / 32)
        f = np.random.default_rng(0).random((32, 32))
        ref = p.solve(f)[0]
        both(lambda: np.testing.assert_array_equal(p.solve(f)[0], ref), 5)
        vp = km.vortex.VortexParticles(np.random.default_rng(1).random((200, 2)), np.ones(200), 0.05)
        both(lambda: vp.step(1e-3), 5)
    """,
}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_two_threads_on_one_object(name):
    code = PRELUDE + textwrap.dedent(SCENARIOS[name])
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
