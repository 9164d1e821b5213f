"""A 2D vortex-particle method driven by the fast multipole method (km.fmm).

Point vortices x_j with circulations Gamma_j [m^2/s] carry the vorticity
omega(x) = sum_j Gamma_j zeta_delta(x - x_j) of Gaussian cores of radius delta (Lamb-Oseen
blobs). The velocity is the Biot-Savart law, u = K_delta * omega, with

    K(x) = (-y, x) / (2 pi |x|^2),    K_delta(x) = K(x) (1 - exp(-|x|^2 / delta^2)).

The singular part is the rotated gradient of the FMM potential phi = sum_j Gamma_j log|x - x_j|:
u = (-d phi/dy, d phi/dx) / (2 pi); the core correction (K_delta - K), which is below 1e-15 of
K beyond 6 delta, is added for the pairs closer than that. Time integration: classical RK4
(Cottet & Koumoutsakos, "Vortex Methods", 2000, ch. 2).

Invariants of the inviscid flow, tracked by the tests: the total circulation sum_j Gamma_j
(exactly, the Gamma_j never change) and the linear impulse I = sum_j Gamma_j (y_j, -x_j), which
K's antisymmetry conserves (each RK stage velocity has sum_j Gamma_j u_j = 0 up to the FMM's eps).
No stability limit is checked: RK4 needs dt |lambda| < 2.8 for the eigenvalues lambda of the
velocity gradient (up to sum_j |Gamma_j| / (2 pi delta^2) where vortices crowd within delta), a
property of the configuration; a blow-up raises km.DivergenceError.
"""

from __future__ import annotations

import time as _time

import numpy as np

from kinema import _core, _stepping, fmm
from kinema._checks import (
    as_float_array, checked_state, finite, finite_result, integer, positive, representable,
    simulation_object, spacing)

__all__ = ["VortexParticles", "merging_patches", "VortexParticles3D", "ring", "thick_ring", "saffman_speed"]

# Beyond this many core radii exp(-r^2/delta^2) < 1e-15: the core correction is dropped.
_CORE_CUTOFF = 6.0


@simulation_object
class VortexParticles:
    """Point vortices with Gaussian cores, advanced by RK4 with FMM velocities.

    x: (n, 2) positions [m] (a writable array, the state). circulation: (n,) Gamma_j [m^2/s].
    core: core radius delta [m]. eps: relative accuracy of the FMM velocity.
    Attributes: x, circulation, core, eps, time [s], steps (count).
    """

    parameters = ("circulation", "core")

    def __init__(self, x, circulation, core, *, eps=1e-10):
        self.x = as_float_array(x, "x", ndim=2).copy()
        if self.x.shape[1] != 2:
            raise ValueError(f"x: expected shape (n, 2), got {self.x.shape}")
        if self.x.size and np.abs(self.x).max() > 1e100:
            raise ValueError("x: positions beyond 1e100 (velocities ~ circulation / distance and their "
                             "squares would over- or underflow); choose other units")
        self.circulation = as_float_array(circulation, "circulation", ndim=1).copy()
        if self.circulation.shape != (len(self.x),):
            raise ValueError(f"circulation: expected shape ({len(self.x)},), got {self.circulation.shape}")
        self.core = spacing(core, "core")
        self.eps = fmm._eps(eps)
        self.time = 0.0
        self.steps = 0

    def velocity(self, points=None) -> np.ndarray:
        """u induced by the vortices at the particles (each one's own term left out), or at
        `points` (m, 2) [m]: (n or m, 2) [m/s], as VortexParticles3D.velocity."""
        if points is None:
            return self._velocity(self.x)
        tgt = as_float_array(points, "points", ndim=2)
        if tgt.shape[1] != 2:
            raise ValueError(f"points: expected shape (m, 2), got {tgt.shape}")
        if tgt.size and np.abs(tgt).max() > 1e100:
            raise ValueError("points: positions beyond 1e100 (as x: distances squared would overflow); "
                             "choose other units")
        return finite_result(self._velocity(self.x, tgt), "velocity")

    def _velocity(self, x, targets=None):
        """u at the vortices placed at x (the RK stages), or at `targets` (checked)."""
        try:
            _, grad = fmm.laplace2d(x, self.circulation, targets, eps=self.eps, gradient=True)
        except ValueError as exc:
            if "overflows" not in str(exc):
                raise
            raise ValueError("x, circulation: the induced velocity overflows float64 (particles too close "
                             "for their circulation, or values too large); choose other units") from None
        u = np.empty_like(grad)
        u[:, 0] = -grad[:, 1]
        u[:, 1] = grad[:, 0]
        if targets is None:
            self._core_correction(x, u)
        else:
            self._core_correction_at(x, targets, u)
        return u / (2 * np.pi)

    def _core_correction(self, x, u):
        # The C++ cell-grid search (GIL released): scipy.spatial's cKDTree costs ~0.5 s to
        # import (its package pulls in scipy.special and qhull) on the first step.
        pairs = _core.sph.neighbor_pairs(x, _CORE_CUTOFF * self.core)
        if len(pairs) == 0:
            return
        i, j = pairs[:, 0], pairs[:, 1]
        d = x[i] - x[j]
        r2 = np.einsum("ij,ij->i", d, d)
        # (K_delta - K)(d) * 2 pi = -(-dy, dx)/r^2 exp(-r^2/delta^2); 0 for coincident pairs,
        # which the FMM leaves out as well.
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(r2 > 0, -np.exp(-r2 / self.core**2) / r2, 0.0)
        kx, ky = -d[:, 1] * w, d[:, 0] * w
        np.add.at(u[:, 0], i, self.circulation[j] * kx)
        np.add.at(u[:, 1], i, self.circulation[j] * ky)
        np.add.at(u[:, 0], j, -self.circulation[i] * kx)
        np.add.at(u[:, 1], j, -self.circulation[i] * ky)

    def _core_correction_at(self, x, targets, u):
        from scipy.spatial import cKDTree

        if len(x) == 0 or len(targets) == 0:
            return
        near = cKDTree(targets).sparse_distance_matrix(cKDTree(x), _CORE_CUTOFF * self.core,
                                                       output_type="ndarray")
        i, j = near["i"], near["j"]  # target i, vortex j
        d = targets[i] - x[j]
        r2 = np.einsum("ij,ij->i", d, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(r2 > 0, -np.exp(-r2 / self.core**2) / r2, 0.0)
        np.add.at(u[:, 0], i, self.circulation[j] * -d[:, 1] * w)
        np.add.at(u[:, 1], i, self.circulation[j] * d[:, 0] * w)

    def step(self, dt) -> _core.StepStats:
        """One classical RK4 step of dx/dt = u(x); returns its StepStats (time, dt, seconds)."""
        dt = positive(dt, "dt")
        start = _time.perf_counter()
        from kinema.errors import DivergenceError

        x0 = self.x
        try:
            k1 = self._velocity(x0)
            k2 = self._velocity(x0 + 0.5 * dt * k1)
            k3 = self._velocity(x0 + 0.5 * dt * k2)
            k4 = self._velocity(x0 + dt * k3)
        except ValueError as exc:  # a stage left the representable range (x stays as it was)
            raise DivergenceError(f"vortex positions: a stage of the step to t = {self.time + dt:g} "
                                  f"overflowed ({exc}); reduce dt (now {dt:g})") from None
        x = x0 + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if not np.isfinite(x).all():
            raise DivergenceError(f"vortex positions: non-finite after the step to t = {self.time + dt:g}; "
                                  f"reduce dt (now {dt:g})")
        self.x = x
        self.time += dt
        self.steps += 1
        return _core.StepStats(time=self.time, dt=dt, seconds=_time.perf_counter() - start)

    def advance(self, duration, dt, *, callback=None):
        """Steps of dt up to `duration` [s], the last landing on it (a remainder under dt/10 is
        absorbed by stretching the last step, the rule of every method)."""
        return _stepping.advance(self, duration, dt, callback)

    def state(self) -> dict:
        """Copies of x, time and steps (RK4 reads nothing else from the past)."""
        return {"x": self.x.copy(), "time": np.array(self.time), "steps": np.array(self.steps)}

    def set_state(self, state: dict) -> None:
        """Restores a :meth:`state` exactly; a refused dict changes nothing."""
        x, time, steps = checked_state(state, ("x",), self.x.shape)
        self.x = x.copy()
        self.time, self.steps = time, steps

    def total_circulation(self) -> float:
        """sum_j Gamma_j [m^2/s]."""
        return float(self.circulation.sum())

    def linear_impulse(self) -> np.ndarray:
        """I = sum_j Gamma_j (y_j, -x_j) [m^3/s] (per unit density)."""
        return np.array([np.dot(self.circulation, self.x[:, 1]), -np.dot(self.circulation, self.x[:, 0])])


def merging_patches(n_per_patch=2000, separation=0.6, radius=0.3, *, seed=0):
    """Two co-rotating Gaussian vortex patches (unit circulation each), as particles; close
    enough (patch width over separation above ~0.3, Meunier et al. 2005) to merge.

    Returns (x, circulation, core): particles on a jittered lattice in each disc, carrying the
    vorticity of a Gaussian of width radius/2 times their area, and a core radius of about the
    particle spacing (overlapping cores, as vortex methods need).
    """
    rng = np.random.default_rng(seed)
    spacing = radius * np.sqrt(np.pi / n_per_patch)
    g = np.arange(-radius, radius + spacing, spacing)
    X, Y = np.meshgrid(g, g, indexing="ij")
    disc = np.c_[X.ravel(), Y.ravel()]
    disc = disc[np.hypot(disc[:, 0], disc[:, 1]) <= radius]
    disc += rng.uniform(-0.05, 0.05, disc.shape) * spacing
    sigma = radius / 2
    w = np.exp(-np.sum(disc**2, axis=1) / (2 * sigma**2))
    gamma = w / w.sum()  # unit circulation per patch
    x = np.r_[disc + [-separation / 2, 0.0], disc + [separation / 2, 0.0]]
    circulation = np.r_[gamma, gamma]
    return x, circulation, 1.5 * spacing


# ---------------------------------------------------------------------------------------- 3D

_INV_4PI = 1.0 / (4.0 * np.pi)
# Leaves at least this many core radii wide: pairs in non-adjacent leaves are that far apart,
# where erf(r/core) = 1 to 2e-17, so the far field's 1/r needs no core correction.
_CORE_WIDTH_3D = 6.0


@simulation_object
class VortexParticles3D:
    """3D vortex particles with Gaussian cores, RK4, velocities by the 3D FMM.

    Particle j carries the vector strength alpha_j = omega_j vol_j [m^3/s] spread as the
    Gaussian zeta(r) = exp(-r^2/core^2) / (pi^{3/2} core^3). The velocity is u = curl psi with
    the vector potential psi(x) = (1/4 pi) sum_j alpha_j erf(r/core)/r (r = |x - x_j|), i.e. the
    regularised Biot-Savart law

        u(x) = -(1/4 pi) sum_j q(r/core) (x - x_j) x alpha_j / r^3,  q(rho) = erf(rho) - 2 rho exp(-rho^2)/sqrt(pi)

    (Winckelmans & Leonard 1993, J. Comput. Phys. 109:247). The three components of psi, their
    gradients and Hessians come from one FMM call (C++, GIL released): the far field with the
    1/r expansions, the near field (adjacent leaves, never narrower than 6 cores) with the
    erf kernel, which is the regularisation applied as a near-field correction. The strengths
    evolve by the classical stretching term d alpha_j/dt = (alpha_j . grad) u(x_j); positions
    and strengths advance together by classical RK4.

    x: (n, 3) positions [m] and strength: (n, 3) alpha [m^3/s] (writable arrays, the state;
    n = 0 is a valid system whose steps change nothing, as in 2D);
    core: radius [m]; eps: relative accuracy of the FMM. time [s].
    """

    parameters = ("strength", "core")

    def __init__(self, x, strength, core, *, eps=1e-10):
        self.x = as_float_array(x, "x", ndim=2).copy()
        if self.x.shape[1] != 3:  # n = 0 is a valid (empty) system, as in 2D
            raise ValueError(f"x: expected shape (n, 3), got {self.x.shape}")
        self.strength = as_float_array(strength, "strength", ndim=2).copy()
        if self.strength.shape != self.x.shape:
            raise ValueError(f"strength: expected shape {self.x.shape} (as x), got {self.strength.shape}")
        self.core = positive(core, "core")
        self.eps = fmm._eps(eps)
        self.time = 0.0
        self.steps = 0

    def _psi(self, x, alpha, targets, derivatives):
        n = len(x)
        m = n if targets is None else len(targets)
        out, _ = fmm._eval3d(x, alpha, targets, eps=self.eps, derivatives=derivatives,
                             kernel="gaussian", length=self.core,
                             min_width=_CORE_WIDTH_3D * self.core, direct=n * m <= 1_000_000)
        return out * _INV_4PI

    @staticmethod
    def _curl(out):
        # out[:, k, 1 + a] = d psi_k / d x_a
        g = out[:, :, 1:4]
        return np.stack([g[:, 2, 1] - g[:, 1, 2], g[:, 0, 2] - g[:, 2, 0], g[:, 1, 0] - g[:, 0, 1]], axis=1)

    def _rates(self, x, alpha):
        out = self._psi(x, alpha, None, 2)
        u = self._curl(out)
        # grad u: d u_i / d x_b from the Hessians H[k][a][b] of psi_k (xx xy xz yy yz zz).
        h = out[:, :, 4:10]
        idx = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
        H = h[:, :, idx]  # (n, 3 components k, 3, 3)
        grad_u = np.stack([H[:, 2, 1, :] - H[:, 1, 2, :], H[:, 0, 2, :] - H[:, 2, 0, :],
                           H[:, 1, 0, :] - H[:, 0, 1, :]], axis=1)  # (n, i, b)
        stretch = np.einsum("nib,nb->ni", grad_u, alpha)
        return u, stretch

    def velocity(self, points=None) -> np.ndarray:
        """u at the particles, or at `points` (m, 3): (m, 3) [m/s]."""
        tgt = None
        if points is not None:
            tgt = as_float_array(points, "points", ndim=2)
            if tgt.shape[1] != 3:
                raise ValueError(f"points: expected shape (m, 3), got {tgt.shape}")
        return finite_result(self._curl(self._psi(self.x, self.strength, tgt, 1)), "velocity")

    def step(self, dt) -> _core.StepStats:
        """One classical RK4 step of dx/dt = u, d alpha/dt = (alpha . grad) u; returns its
        StepStats (time at the end [s], dt [s], wall seconds)."""
        dt = positive(dt, "dt")
        start = _time.perf_counter()
        x0, a0 = self.x, self.strength
        k1 = self._rates(x0, a0)
        k2 = self._rates(x0 + 0.5 * dt * k1[0], a0 + 0.5 * dt * k1[1])
        k3 = self._rates(x0 + 0.5 * dt * k2[0], a0 + 0.5 * dt * k2[1])
        k4 = self._rates(x0 + dt * k3[0], a0 + dt * k3[1])
        x1 = x0 + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        a1 = a0 + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        if not (np.isfinite(x1).all() and np.isfinite(a1).all()):
            from kinema.errors import DivergenceError

            raise DivergenceError(f"vortex positions/strengths: non-finite at step {self.steps + 1} "
                                  f"(t = {self.time + dt:g}); reduce dt (now {dt:g})")
        self.x[...] = x1
        self.strength[...] = a1
        self.time += dt
        self.steps += 1
        return _core.StepStats(time=self.time, dt=dt, seconds=_time.perf_counter() - start)

    def advance(self, duration, dt, *, callback=None):
        """Steps of dt up to `duration` [s], the last landing on it (a remainder under dt/10 is
        absorbed by stretching the last step, the rule of every method)."""
        return _stepping.advance(self, duration, dt, callback)

    def linear_impulse(self) -> np.ndarray:
        """I = 1/2 sum_j x_j x alpha_j (3,) [m^4/s] (per unit density)."""
        return finite_result(0.5 * np.cross(self.x, self.strength).sum(axis=0), "linear_impulse")

    def total_strength(self) -> np.ndarray:
        """sum_j alpha_j (3,) [m^3/s] (zero for closed vortex lines)."""
        return self.strength.sum(axis=0)

    def state(self) -> dict:
        """Copies of x, strength, time and steps (RK4 reads nothing else from the past)."""
        return {"x": self.x.copy(), "strength": self.strength.copy(), "time": np.array(self.time),
                "steps": np.array(self.steps)}

    def set_state(self, state: dict) -> None:
        """Restores a :meth:`state` exactly; a refused dict changes nothing."""
        x, strength, time, steps = checked_state(state, ("x", "strength"), self.x.shape)
        self.x[...] = x
        self.strength[...] = strength
        self.time, self.steps = time, steps


# Largest ring drawn by ring() and thick_ring() (particles; a few GB of float64 arrays).
MAX_RING_PARTICLES = 10**8


def ring(radius, core, circulation, n, *, center=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0)):
    """A thin vortex ring as n particles on a circle: (x (n, 3), strength (n, 3)).

    Each particle carries alpha = circulation * (2 pi radius / n) * tangent, the tangent turning
    positively about `axis`, so a positive circulation moves the ring along +axis at about
    Saffman's (1970) speed U = circulation / (4 pi radius) (ln(8 radius / core) - 0.558).
    The particle spacing should stay below the core radius (overlapping cores).
    """
    radius = spacing(radius, "radius")
    spacing(core, "core")
    circulation = finite(circulation, "circulation")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        raise ValueError(f"n: expected an integer >= 3, got {n!r}")
    integer(n, "n", high=MAX_RING_PARTICLES)
    c = as_float_array(center, "center", ndim=1)
    ax = as_float_array(axis, "axis", ndim=1)
    if c.shape != (3,):
        raise ValueError(f"center: expected 3 coordinates, got shape {c.shape}")
    if ax.shape != (3,) or not np.linalg.norm(ax) > 0:
        raise ValueError(f"axis: expected a nonzero 3-vector, got {axis!r}")
    ez = ax / np.linalg.norm(ax)
    helper = np.array([1.0, 0, 0]) if abs(ez[0]) < 0.9 else np.array([0, 1.0, 0])
    ex = np.cross(helper, ez)
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    theta = 2 * np.pi * np.arange(n) / n
    x = c + radius * (np.cos(theta)[:, None] * ex + np.sin(theta)[:, None] * ey)
    tangent = -np.sin(theta)[:, None] * ex + np.cos(theta)[:, None] * ey
    with np.errstate(all="ignore"):
        strength = circulation * (2 * np.pi * radius / n) * tangent
    representable(x, "radius, center", "the positions")
    representable(strength, "radius, circulation", "the strengths")
    return x, strength


def thick_ring(radius, core, circulation, n, *, layers=3, center=(0.0, 0.0, 0.0),
               axis=(0.0, 0.0, 1.0)):
    """A vortex ring whose Gaussian core exp(-r^2/core^2) is resolved by particles.

    The cross-section holds `layers` circles of 6, 12, ... particles around a central one,
    spacing h = 2 core / layers; each particle's own core is h (overlapping), and the circulation
    is spread with weights exp(-rho^2/(core^2 - h^2)) so that the sum of the Gaussian blobs is a
    Gaussian of width `core` (Gaussians of widths a and b convolve to sqrt(a^2 + b^2)).
    n particles per circle along the ring. Returns (x, strength, particle_core).
    """
    radius = spacing(radius, "radius")
    core = spacing(core, "core")
    circulation = finite(circulation, "circulation")
    if isinstance(layers, bool) or not isinstance(layers, (int, np.integer)) or layers < 1:
        raise ValueError(f"layers: expected an integer >= 1, got {layers!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 3:
        raise ValueError(f"n: expected an integer >= 3, got {n!r}")
    integer(layers, "layers", high=1000)
    if n * (1 + 3 * layers * (layers + 1)) > MAX_RING_PARTICLES:
        raise ValueError(f"n, layers: {n} x {1 + 3 * layers * (layers + 1)} particles is more than "
                         f"{MAX_RING_PARTICLES}")
    h = 2.0 * core / layers
    width2 = core**2 - h**2
    if width2 <= 0:
        raise ValueError("layers: expected at least 3 (the particle cores must be narrower than core)")
    rho, phi, area = [0.0], [0.0], [np.pi * (h / 2) ** 2]
    for i in range(1, layers + 1):
        k = 6 * i
        rho += [i * h] * k
        phi += list(2 * np.pi * (np.arange(k) + 0.5 * (i % 2)) / k)
        area += [2 * np.pi * i * h * h / k] * k
    rho, phi, area = map(np.asarray, (rho, phi, area))
    weights = np.exp(-rho**2 / width2) * area
    weights *= float(circulation) / weights.sum()
    x0, a0 = ring(radius, core, 1.0, n, center=(0.0, 0.0, 0.0), axis=axis)
    ez = np.asarray(axis, float) / np.linalg.norm(axis)
    radial_dir = x0 / radius
    xs, alphas = [], []
    for r_, p_, w_ in zip(rho, phi, weights):
        offset = r_ * (np.cos(p_) * radial_dir + np.sin(p_) * ez)
        scale = (radius + r_ * np.cos(p_)) / radius  # the line element at that radius
        xs.append(x0 + offset)
        alphas.append(a0 * w_ * scale)
    c = as_float_array(center, "center", ndim=1)
    with np.errstate(all="ignore"):
        x, alpha = np.concatenate(xs) + c, np.concatenate(alphas)
    representable(x, "radius, center", "the positions")
    representable(alpha, "radius, circulation", "the strengths")
    return x, alpha, h


def saffman_speed(radius, core, circulation):
    """Saffman's (1970) speed of a thin ring with a Gaussian core exp(-r^2/core^2):
    U = circulation / (4 pi radius) (ln(8 radius/core) - (1 - gamma + ln 2)/2), with
    (1 - gamma + ln 2)/2 = 0.558 (gamma: Euler's constant)."""
    const = 0.5 * (1 - np.euler_gamma + np.log(2))
    return circulation / (4 * np.pi * radius) * (np.log(8 * radius / core) - const)
