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
"""

from __future__ import annotations

import numpy as np

from kinema import fmm
from kinema._checks import as_float_array, positive, simulation_object, spacing

__all__ = ["VortexParticles", "merging_patches"]

# Beyond this many core radii exp(-r^2/delta^2) < 1e-15: the core correction is dropped.
_CORE_CUTOFF = 6.0


@simulation_object
class VortexParticles:
    """Point vortices with Gaussian cores, advanced by RK4 with FMM velocities.

    x: (n, 2) positions [m] (a writable array, the state). circulation: (n,) Gamma_j [m^2/s].
    core: core radius delta [m]. eps: relative accuracy of the FMM velocity.
    """

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

    def velocity(self, x=None) -> np.ndarray:
        """u at the particles (or at the vortex positions `x`, for the RK stages): (n, 2) [m/s]."""
        x = self.x if x is None else x
        try:
            _, grad = fmm.laplace2d(x, self.circulation, eps=self.eps, gradient=True)
        except ValueError as exc:
            if "overflows" not in str(exc):
                raise
            raise ValueError("x, circulation: the induced velocity overflows float64 (particles too close "
                             "for their circulation, or values too large); choose other units") from None
        u = np.empty_like(grad)
        u[:, 0] = -grad[:, 1]
        u[:, 1] = grad[:, 0]
        self._core_correction(x, u)
        return u / (2 * np.pi)

    def _core_correction(self, x, u):
        from scipy.spatial import cKDTree

        pairs = cKDTree(x).query_pairs(_CORE_CUTOFF * self.core, output_type="ndarray")
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

    def step(self, dt):
        """One classical RK4 step of dx/dt = u(x)."""
        dt = positive(dt, "dt")
        from kinema.errors import DivergenceError

        x0 = self.x
        try:
            k1 = self.velocity(x0)
            k2 = self.velocity(x0 + 0.5 * dt * k1)
            k3 = self.velocity(x0 + 0.5 * dt * k2)
            k4 = self.velocity(x0 + dt * k3)
        except ValueError as exc:  # a stage left the representable range (x stays as it was)
            raise DivergenceError(f"vortex positions: a stage of the step to t = {self.time + dt:g} "
                                  f"overflowed ({exc}); reduce dt (now {dt:g})") from None
        x = x0 + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if not np.isfinite(x).all():
            raise DivergenceError(f"vortex positions: non-finite after the step to t = {self.time + dt:g}; "
                                  f"reduce dt (now {dt:g})")
        self.x = x
        self.time += dt

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
