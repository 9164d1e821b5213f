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

from kinema._checks import (as_float_array, choice, grid_array, grid_shape, positive, positive_int, representable,
                            spacing)
from kinema.errors import DivergenceError, StabilityError
from kinema.poisson import Solver

__all__ = ["step", "Stepper", "stable_dt", "SCHEMES"]

SCHEMES = ("ftcs", "implicit", "crank_nicolson")


def stable_dt(h, kappa, d) -> float:
    """Largest FTCS step: dt = h^2 / (2 d kappa) [s]."""
    if isinstance(d, bool) or d not in (2, 3):
        raise ValueError(f"d: expected 2 or 3, got {d!r}")
    return float(representable(spacing(h, "h") ** 2 / (2 * d * positive(kappa, "kappa")), "h, kappa", "h^2 / kappa"))


class Stepper:
    """Advances temperature fields of one grid by a fixed scheme and time step.

    Builds the shifted Poisson solver (and its multigrid hierarchy) once, so that stepping
    many frames costs only the solves. Arguments as in :func:`step`; ``shape`` is the grid.
    """

    def __init__(self, shape, kappa, dt, h, scheme="implicit", bc="neumann", *, check=True,
                 tol=1e-10, solid=None):
        self.kappa = positive(kappa, "kappa")
        self.dt = positive(dt, "dt")
        self.h = spacing(h, "h")
        self.scheme = choice(scheme, "scheme", SCHEMES)
        self.tol = positive(tol, "tol")
        d = len(grid_shape(shape, "shape"))  # (a bare int raised TypeError from len)
        self._c = self.kappa * self.dt
        if not (np.isfinite(self._c) and np.isfinite(1 / self._c) if self._c > 0 else False):
            raise ValueError(f"kappa, dt: kappa*dt = {self.kappa}*{self.dt} is not representable as a "
                             "positive float64 with a finite inverse; choose other units")
        if scheme == "ftcs":
            ratio = self._c / self.h**2
            if check and ratio > 1 / (2 * d):
                raise StabilityError(
                    f"dt: FTCS is unstable for kappa*dt/h^2 = {ratio:.4g} > 1/(2d) = {1 / (2 * d):.4g}; "
                    f"use dt <= {stable_dt(self.h, self.kappa, d):.4g} s or scheme='implicit'")
            self._solver = Solver(shape, self.h, bc, method="cg", solid=solid)
        else:
            self._shift = 1 / self._c if scheme == "implicit" else 2 / self._c
            self._solver = Solver(shape, self.h, bc, method="mgpcg", solid=solid, shift=self._shift)
        self.shape = self._solver.shape

    def step(self, T, steps=1):
        """Returns T advanced by ``steps`` steps (a new array; T is not modified)."""
        T = as_float_array(T, "T")
        if T.shape != self.shape:
            raise ValueError(f"T: expected shape {self.shape}, got {T.shape}")
        steps = positive_int(steps, "steps")  # a long run answers Ctrl-C between steps
        out = T.copy()
        if self.scheme == "ftcs":
            self._solver._core.explicit_steps(out, self._c, steps)
            if not np.isfinite(out).all():
                d = len(self.shape)
                raise DivergenceError(
                    f"T: non-finite temperature after {steps} FTCS steps (kappa*dt/h^2 = "
                    f"{self._c / self.h**2:.4g}); the stable limit is dt <= "
                    f"{stable_dt(self.h, self.kappa, d):.4g} s")
            return out
        for _ in range(steps):
            if self.scheme == "implicit":
                rhs = self._shift * out
            else:
                rhs = 2 * self._shift * out - self._solver.apply(out)  # apply() includes the shift
            if not np.isfinite(rhs).all():
                raise ValueError("T: the implicit scheme's right-hand side overflows float64 for these "
                                 "temperatures; scale T into a smaller range")
            out, _info = self._solver.solve(rhs, tol=self.tol, x0=out)
        return out


def step(T, kappa, dt, h, scheme="implicit", bc="neumann", steps=1, check=True, *, tol=1e-10,
         solid=None):
    """Advances the temperature field ``T`` by ``steps`` steps of ``dt``; returns the new field.

    T: (nx, ny[, nz]) temperatures [K]. kappa: diffusivity [m^2/s]. dt: time step [s].
    h: cell size [m]. scheme: "ftcs", "implicit" or "crank_nicolson". bc: "neumann" or
    "dirichlet". check: for "ftcs", raise StabilityError above the stability limit.
    tol: relative residual of each implicit solve. solid: optional bool mask of insulated
    cells excluded from the domain (T is 0 there). For many calls on one grid, a
    :class:`Stepper` keeps the solver between them.
    """
    T = grid_array(T, "T")
    stepper = Stepper(T.shape, kappa, dt, h, scheme, bc, check=check, tol=tol, solid=solid)
    return stepper.step(T, steps)
