"""km.grid forward flows with closed forms: gravity-driven Poiseuille flow (2D, second order),
flow in a square duct against its series solution (3D), and Couette flow under a moving lid,
each in a channel open at both ends (open=("x-", "x+")); a periodic shear wave decaying at the
implicit viscosity's exact rate (2D, 3D); mirror symmetry of a buoyant plume."""

import numpy as np
import pytest

import kinema as km


# ----------------------------------------------------------------------------- channel flows

def channel(shape, h, *, nu=0.5, gravity=None, steps=60, dt=0.05):
    """A no-slip channel open at x- and x+ (p = 0 there): walls on the other sides only."""
    f = km.grid.Fluid(shape, h, viscosity=nu, walls="no_slip", open=("x-", "x+"), gravity=gravity,
                      advection="semi_lagrangian")
    return f, steps, dt


def test_gravity_driven_poiseuille_flow_converges_at_second_order():
    # Body force g along a channel of height H with open ends: steady u = g y (H - y) / (2 nu),
    # reached after many viscous times H^2 / (pi^2 nu) = 0.2 s (3 s run). The no-slip ghost
    # (u = -u across the wall) makes the error O(h^2): 1.6e-2, 3.9e-3, 9.8e-4 measured.
    g, nu, H = 1.0, 0.5, 1.0
    errors = []
    for ny in (8, 16, 32):
        h = H / ny
        f, steps, dt = channel((2 * ny, ny), h, nu=nu, gravity=(g, 0.0))
        for _ in range(steps):
            f.step(dt)
        y = (np.arange(ny) + 0.5) * h
        exact = g / (2 * nu) * y * (H - y)
        errors.append(np.abs(f.u[ny] - exact).max() / exact.max())
        assert np.abs(f.v).max() < 1e-8 * exact.max()
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert (np.abs(rates - 2) < 0.1).all() and errors[-1] < 2e-3, f"errors {errors}, rates {rates}"


def test_duct_flow_3d_against_its_series_solution():
    # A square duct of side H: -nu lap u = g with u = 0 on the walls, solved by the double
    # sine series u = sum_{m,n odd} 16 g / (pi^2 m n nu k^2) sin(m pi y/H) sin(n pi z/H),
    # k^2 = (m^2 + n^2) pi^2 / H^2. Second order: 4.1e-2 at n = 6, 1.1e-2 at n = 12.
    g, nu, H = 1.0, 0.5, 1.0
    errors = []
    for n in (6, 12):
        h = H / n
        f, steps, dt = channel((2 * n, n, n), h, nu=nu, gravity=(g, 0.0, 0.0), steps=40)
        for _ in range(steps):
            f.step(dt)
        Y, Z = np.meshgrid((np.arange(n) + 0.5) * h, (np.arange(n) + 0.5) * h, indexing="ij")
        exact = np.zeros_like(Y)
        for a in range(1, 80, 2):
            for b in range(1, 80, 2):
                k2 = (a * a + b * b) * np.pi**2 / H**2
                exact += 16 * g / (np.pi**2 * a * b * nu * k2) * np.sin(a * np.pi * Y / H) * np.sin(b * np.pi * Z / H)
        errors.append(np.abs(f.u[n] - exact).max() / exact.max())
        assert max(np.abs(f.v).max(), np.abs(f.w).max()) < 1e-8 * exact.max()
    rate = np.log2(errors[0] / errors[1])
    assert abs(rate - 2) < 0.2 and errors[-1] < 0.015, f"errors {errors}, rate {rate:.2f}"


def test_couette_flow_under_a_moving_lid_is_linear():
    # A lid at y = H sliding at U over an open-ended channel: u = U y / H, which the MAC
    # stencil and the moving-wall ghost represent exactly (error at the solve's tolerance,
    # 1.4e-7 measured with the default tol 1e-6), at the inlet column as in the middle.
    U, H, n = 2.0, 1.0, 16
    f, steps, dt = channel((3 * n, n), H / n, steps=80)
    f.set_wall_velocity("y+", (U, 0.0))
    for _ in range(steps):
        f.step(dt)
    exact = U * (np.arange(n) + 0.5) / n
    for column in (1, 3 * n // 2):
        assert np.abs(f.u[column] - exact).max() < 1e-5 * U


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("advection", ["semi_lagrangian", "maccormack"])
def test_periodic_shear_wave_decays_at_the_backward_euler_rate(d, advection):
    # u = sin(k z) (z the last axis) is divergence free and advects into itself, so only the
    # implicit viscosity acts on it: each step divides it by 1 + nu dt lam_h with the discrete
    # eigenvalue lam_h = 4/h^2 sin^2(k h / 2). Exact to rounding, in 2D and 3D.
    n, nu, dt, steps = 16, 0.3, 0.01, 10
    h, k = 1.0 / n, 2 * np.pi
    f = km.grid.Fluid((n,) * d, h, boundary="periodic", viscosity=nu, advection=advection, tol=1e-12)
    profile = np.sin(k * (np.arange(n) + 0.5) * h)
    f.u[...] = profile
    for _ in range(steps):
        f.step(dt)
    lam = 4 / h**2 * np.sin(k * h / 2) ** 2
    expected = profile / (1 + nu * dt * lam) ** steps
    assert np.abs(f.u - expected).max() < 1e-13


def test_mirrored_plume_rises_as_the_mirror_image():
    # A warm blob left of the centre line and its mirror image right of it: the temperature
    # and the horizontal velocity are mirror images (u antisymmetric) to the pressure
    # solve's tolerance 1e-10 (measured 2e-12).
    def plume(mirror):
        f = km.grid.Fluid((32, 48), 1 / 32, density=True, temperature=True, buoyancy=(0.0, 2.0),
                          gravity=(0, -9.81), tol=1e-10)
        c = (np.arange(32) + 0.5) / 32
        T0 = np.exp(-((c[:, None] - 0.4) ** 2 + ((np.arange(48) + 0.5) / 32 - 0.3)[None, :] ** 2) / 0.01)
        f.temperature[...] = T0[::-1] if mirror else T0
        for _ in range(20):
            f.step(0.02)
        return f

    a, b = plume(False), plume(True)
    scale = np.abs(a.u).max()
    assert scale > 0.05
    assert np.abs(a.temperature - b.temperature[::-1]).max() < 1e-9
    assert np.abs(a.u + b.u[::-1]).max() < 1e-9
    assert np.abs(a.v - b.v[::-1]).max() < 1e-9
