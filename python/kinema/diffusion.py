"""Heat diffusion dT/dt = kappa lap(T) on cell-centred grids (2D and 3D).

Schemes, in time step dt with c = kappa dt and A = -lap_h (:mod:`kinema.poisson`'s operator):

* ``"ftcs"``: forward Euler, T' = T - c A T. Stable only for kappa dt / h^2 <= 1/(2d); beyond
  that ``check=True`` raises :class:`kinema.StabilityError` naming the largest stable dt.
* ``"implicit"``: backward Euler, (I + c A) T' = T. First order, unconditionally stable.
* ``"crank_nicolson"``: (I + c/2 A) T' = (I - c/2 A) T. Second order, unconditionally stable
  (but, unlike backward Euler, it damps the stiffest modes only weakly: they flip sign).

Both implicit schemes solve the shifted Poisson problem (s I + A) T' = rhs with s = 1/c or 2/c
by multigrid-preconditioned CG (:class:`kinema.poisson.Solver` with ``shift=s``).
Boundaries: ``bc="neumann"`` (insulated, total heat conserved) or ``"dirichlet"`` (T = 0 on the
boundary faces).
"""

from __future__ import annotations

import numpy as np

from kinema._checks import as_float_array, choice, positive, positive_int
from kinema.errors import DivergenceError, StabilityError
from kinema.poisson import Solver

__all__ = ["step", "stable_dt", "SCHEMES"]

SCHEMES = ("ftcs", "implicit", "crank_nicolson")


def stable_dt(h, kappa, d) -> float:
    """Largest FTCS step: dt = h^2 / (2 d kappa) [s]."""
    return positive(h, "h") ** 2 / (2 * d * positive(kappa, "kappa"))


def step(T, kappa, dt, h, scheme="implicit", bc="neumann", steps=1, check=True, *, tol=1e-10,
         solid=None):
    """Advances the temperature field ``T`` by ``steps`` steps of ``dt``; returns the new field.

    T: (nx, ny[, nz]) temperatures [K]. kappa: diffusivity [m^2/s]. dt: time step [s].
    h: cell size [m]. scheme: "ftcs", "implicit" or "crank_nicolson". bc: "neumann" or
    "dirichlet". check: for "ftcs", raise StabilityError above the stability limit.
    tol: relative residual of each implicit solve. solid: optional bool mask of insulated
    cells excluded from the domain (T is 0 there).
    """
    T = as_float_array(T, "T", ndim=(2, 3))
    kappa = positive(kappa, "kappa")
    dt = positive(dt, "dt")
    h = positive(h, "h")
    choice(scheme, "scheme", SCHEMES)
    steps = positive_int(steps, "steps")
    d = T.ndim
    c = kappa * dt
    out = T.copy()
    if scheme == "ftcs":
        ratio = c / h**2
        if check and ratio > 1 / (2 * d):
            raise StabilityError(
                f"dt: FTCS is unstable for kappa*dt/h^2 = {ratio:.4g} > 1/(2d) = {1 / (2 * d):.4g}; "
                f"use dt <= {stable_dt(h, kappa, d):.4g} s or scheme='implicit'")
        solver = Solver(T.shape, h, bc, method="cg", solid=solid)
        solver._core.explicit_steps(out, c, steps)
        if not np.isfinite(out).all():
            raise DivergenceError(
                f"T: non-finite temperature after {steps} FTCS steps (kappa*dt/h^2 = {ratio:.4g}); "
                f"the stable limit is dt <= {stable_dt(h, kappa, d):.4g} s")
        return out

    shift = 1 / c if scheme == "implicit" else 2 / c
    solver = Solver(T.shape, h, bc, method="mgpcg", solid=solid, shift=shift)
    for _ in range(steps):
        if scheme == "implicit":
            rhs = shift * out
        else:
            rhs = 2 * shift * out - solver.apply(out)  # apply() includes the shift: (s I - A) T
        out, _info = solver.solve(rhs, tol=tol, x0=out)
    return out
