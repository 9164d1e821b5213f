"""km.fem: Lagrangian finite elements for elastic solids (linear triangles and tetrahedra).

The deformation gradient of each element is F = Ds Dm^-1 (Dm^-1 and rest volumes precomputed);
2D triangles are plane strain with unit thickness. Energy densities psi(F) (Sifakis & Barbic,
SIGGRAPH course notes 2012), with Lame parameters from :func:`lame`:

- ``"linear"``: mu eps:eps + lam/2 tr(eps)^2, eps = (F + F^T)/2 - I (small strain only);
- ``"stvk"``: mu E:E + lam/2 tr(E)^2, E = (F^T F - I)/2;
- ``"corotated"``: mu ||F - R||^2 + lam/2 (J - 1)^2 (fixed corotated, Stomakhin et al. 2012);
- ``"neohookean"``: mu/2 (tr(F^T F) - d) + lam'/2 (J - alpha)^2 - mu^2/(2 lam') with
  lam' = lam + mu, alpha = 1 + mu/lam' (stable neo-Hookean, Smith, de Goes & Kim 2018): it
  matches the Lame parameters at small strain and stays defined for inverted elements (J <= 0).

Implicit Euler (``Body.step``, default) minimises the incremental potential
g(x) = 1/2 ||x - (x_n + h v_n)||_M^2 + h c/2 ||x - x_n||_M^2 + h^2 (E(x) - M g . x)
by projected Newton: element Hessians vol B^T (dP/dF)+ B with dP/dF's negative eigenvalues
clamped (only for elements whose dP/dF is not already positive definite), assembled in parallel
into a sparsity pattern fixed at construction, solved with CHOLMOD (analysis reused across Newton
iterations and steps, the numeric factor reused as a PCG preconditioner while it stays good) or
CG, with a backtracking line search; converged when ||grad g|| <= tol
times its value at the inertial guess x_n + h v_n. ``integrator="symplectic"`` is the explicit
path (no Hessian is assembled). The damping c [1/s] is mass-proportional.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from kinema import _core
from kinema._checks import (
    as_float_array, choice, finite, finite_result, non_negative, positive, positive_int,
    simulation_object, time_step)
from kinema._state import state_property
from kinema.massspring import _gravity, _indices

__all__ = ["Body", "NewtonInfo", "MODELS", "lame", "psi", "piola", "piola_derivative",
           "rectangle_mesh", "box_mesh"]

MODELS = ("linear", "stvk", "corotated", "neohookean")
_SOLVERS = ("cholmod", "cholmod_direct", "cholmod_pcg", "cg")
_DEFINITENESS = ("adaptive", "project", "none")


@dataclass(frozen=True)
class NewtonInfo:
    """Statistics of one implicit step or static solve.

    iterations: Newton iterations; converged: whether ||grad|| <= tol ||grad_0||.
    gradient_norm: ||grad g|| at every iterate (absolute, [kg m] for a step, [N] static).
    step_length: accepted line-search step of each iteration (1 = full Newton step).
    projected_elements: elements whose dP/dF was clamped in the last iteration.
    cg_iterations: (P)CG iterations; factorizations: CHOLMOD numeric factorisations.
    seconds_assembly (gradient + Hessian), seconds_factor, seconds_solve,
    seconds_line_search, seconds: wall times [s].
    """

    iterations: int
    converged: bool
    gradient_norm: list = field(repr=False)
    step_length: list = field(repr=False)
    projected_elements: int
    cg_iterations: int
    factorizations: int
    seconds_assembly: float
    seconds_factor: float
    seconds_solve: float
    seconds_line_search: float
    seconds: float

    @property
    def residual(self) -> float:
        """Final relative gradient norm ||grad|| / ||grad_0||."""
        g = self.gradient_norm
        return g[-1] / g[0] if g and g[0] > 0 else 0.0


def lame(E, nu):
    """(mu, lam) [Pa] from Young's modulus E [Pa] and Poisson's ratio nu in (-1, 0.5)."""
    E = positive(E, "E")
    nu = finite(nu, "nu")
    if not -1 < nu < 0.5:
        raise ValueError(f"nu: expected a Poisson ratio in (-1, 0.5), got {nu}")
    return _core.fem.lame(E, nu)


def _F_batch(F):
    F = as_float_array(F, "F")
    if F.ndim < 2 or F.shape[-1] != F.shape[-2] or F.shape[-1] not in (2, 3):
        raise ValueError(f"F: expected shape (..., d, d) with d = 2 or 3, got {F.shape}")
    d = F.shape[-1]
    return np.ascontiguousarray(F.reshape(-1, d, d)), F.shape[:-2], d


def _pointwise(F, what, model, mu, lam, project=False):
    choice(model, "model", MODELS)
    mu = positive(mu, "mu")
    lam = finite(lam, "lam")
    batch, lead, d = _F_batch(F)
    out = _core.fem.pointwise(batch, what, model, mu, lam, project)
    if not np.isfinite(out).all():
        bad = int(np.count_nonzero(~np.isfinite(out).reshape(len(batch), -1).all(axis=1)))
        raise ValueError(f"F: {what} is not finite for {bad} of the {len(batch)} deformation gradients "
                         "(an inverted element, det F <= 0, for a model with log J; or values so large "
                         "that the energy overflows)")
    return out.reshape(lead + out.shape[1:])


def psi(F, model, mu, lam):
    """Energy density psi(F) [J/m^d] for F of shape (..., d, d); returns shape (...)."""
    return _pointwise(F, "psi", model, mu, lam)


def piola(F, model, mu, lam):
    """First Piola-Kirchhoff stress P = dpsi/dF [Pa] for F of shape (..., d, d)."""
    return _pointwise(F, "piola", model, mu, lam)


def piola_derivative(F, model, mu, lam, *, project=False):
    """dP/dF as (..., d^2, d^2) matrices on vec(F) (column-major: index c*d + r);
    ``project`` clamps negative eigenvalues (the definiteness fix the Newton solver uses)."""
    return _pointwise(F, "dpdf", model, mu, lam, project)


@simulation_object
class Body:
    """An elastic body of linear triangles (2D, plane strain) or tetrahedra (3D).

    vertices: (n, d) rest positions [m]; elements: (m, d + 1) vertex indices, positively
        oriented (degenerate or inverted rest elements raise ValueError naming the element).
    model: one of MODELS; youngs_modulus [Pa]; poisson_ratio in (-1, 0.5); density [kg/m^d].
    fixed: vertex indices held in place; gravity: (d,) [m/s^2] or None; damping: c [1/s].
    orient: re-orient negatively oriented elements (by :func:`kinema.mesh.orient`) instead of
        refusing them; ``flipped`` then lists the indices of the elements swapped. Flat
        elements (slivers) are still refused: remove them with :func:`kinema.mesh.clean`.

    Attributes: x (n, d) [m] and v (n, d) [m/s] are writable zero-copy views of the body's
    state (valid as long as the body); rest (n, d) [m] is a copy of the rest shape;
    mass (n,) [kg] the lumped vertex masses.
    """

    def __init__(self, vertices, elements, *, model="neohookean", youngs_modulus, poisson_ratio,
                 density, fixed=(), gravity=None, damping=0.0, orient=False):
        vertices = as_float_array(vertices, "vertices", ndim=2)
        n, d = vertices.shape
        if d not in (2, 3):
            raise ValueError(f"vertices: expected shape (n, 2) or (n, 3), got {vertices.shape}")
        elements = _indices(elements, "elements", n, (d + 1,))
        if elements.shape[0] == 0:
            raise ValueError("elements: expected at least one element")
        choice(model, "model", MODELS)
        E = positive(youngs_modulus, "youngs_modulus")
        nu = finite(poisson_ratio, "poisson_ratio")
        if not -1 < nu < 0.5:
            raise ValueError(f"poisson_ratio: expected a value in (-1, 0.5), got {nu}")
        rho = positive(density, "density")
        fixed = _indices(np.asarray(fixed).ravel() if np.size(fixed) else np.zeros(0, np.int64),
                         "fixed", n)
        self.flipped = np.zeros(0, np.int64)
        if orient:
            from kinema import mesh

            elements, self.flipped = mesh.orient(vertices, elements)
        try:
            self._core = _core.fem.Body(vertices, elements, model, E, nu, rho, fixed,
                                        _gravity(gravity, d), non_negative(damping, "damping"))
        except ValueError as exc:
            hint = {"inverted": "; or pass orient=True (km.mesh.orient) to re-orient such elements",
                    "degenerate": "; km.mesh.clean(vertices, elements) removes flat elements (slivers) "
                                  "and says which"}
            for word, extra in hint.items():
                if word in str(exc):
                    raise type(exc)(f"{exc}{extra}") from None
            raise
        self.elements = elements
        self.model = model
        self.fixed = fixed

    x = state_property(lambda self: self._core.x, "x", "(n, d) positions [m] (assigning copies in)")
    v = state_property(lambda self: self._core.v, "v", "(n, d) velocities [m/s] (assigning copies in)")
    rest = property(lambda self: self._core.rest)
    mass = property(lambda self: self._core.mass)
    time = property(lambda self: self._core.time, doc="Simulated time [s].")
    mu = property(lambda self: self._core.mu)
    lam = property(lambda self: self._core.lam)

    @property
    def explicit_dt_limit(self) -> float:
        """2 / omega_max [s], omega_max^2 bounded by Gershgorin on M^-1 K at rest: a conservative
        limit of the symplectic step."""
        return self._core.explicit_dt_limit

    def step(self, dt, integrator="implicit", tol=1e-6, max_newton=50, linear_solver="cholmod",
             *, cg_tol=1e-4, definiteness="adaptive", steps=1):
        """Advances ``steps`` steps of ``dt`` [s].

        implicit: backward Euler by projected Newton (see the module docstring); returns the
        NewtonInfo of the last step. Raises km.ConvergenceError when Newton does not reach
        ``tol`` in ``max_newton`` iterations (the state is then left at the last completed
        step). symplectic: returns None.
        definiteness: "adaptive" (the exact Hessian while CHOLMOD finds it positive definite,
        else the per-element projection: quadratic convergence where possible), "project"
        (always project) or "none" (exact Newton; km.NotPositiveDefiniteError if indefinite).
        With linear_solver="cg" the matrix is always projected.
        linear_solver: "cholmod" (default: CHOLMOD's factorisation of an earlier Newton
        iteration or step as the preconditioner of PCG, solved to the inexact-Newton forcing
        tolerance min(cg_tol, |g_k|/|g_0|), bounded below by what ``tol`` still needs; the
        matrix is refactorised when PCG needs more than 25 iterations or gives no descent
        direction; Newton's stopping test on the gradient is the same for every solver),
        "cholmod_direct" (factorise every Newton iteration, analysis reused), "cholmod_pcg"
        (the lagged factor with the fixed PCG tolerance cg_tol) or "cg" (Jacobi-preconditioned
        CG to cg_tol).
        """
        dt = time_step(dt)
        choice(integrator, "integrator", ("implicit", "symplectic"))
        steps = positive_int(steps, "steps")
        if integrator == "symplectic":
            self._core.step_symplectic(dt, steps)
            return None
        tol = positive(tol, "tol")
        max_newton = positive_int(max_newton, "max_newton")
        choice(linear_solver, "linear_solver", _SOLVERS)
        cg_tol = positive(cg_tol, "cg_tol")
        choice(definiteness, "definiteness", _DEFINITENESS)
        info = None
        for _ in range(steps):
            info = self._core.step_implicit(dt, tol, max_newton, linear_solver, cg_tol, definiteness)
        return NewtonInfo(**info)

    def solve_static(self, tol=1e-8, max_iter=100, load_steps=1, *, linear_solver="cholmod",
                     definiteness="adaptive"):
        """Static equilibrium under gravity and the fixed vertices, from the current x, by
        projected Newton with gravity ramped over ``load_steps``; sets x and v = 0.
        Returns a NewtonInfo (iterations summed over load steps)."""
        info = self._core.solve_static(positive(tol, "tol"), positive_int(max_iter, "max_iter"),
                                       positive_int(load_steps, "load_steps"),
                                       choice(linear_solver, "linear_solver", _SOLVERS),
                                       choice(definiteness, "definiteness", _DEFINITENESS))
        return NewtonInfo(**info)

    def energy(self) -> float:
        """Kinetic + elastic + gravitational energy [J] (per unit thickness in 2D)."""
        c = self._core
        return finite_result(c.kinetic_energy() + c.elastic_energy() + c.gravity_energy(), "energy")

    def elastic_energy(self) -> float:
        return finite_result(self._core.elastic_energy(), "elastic_energy")

    def kinetic_energy(self) -> float:
        return finite_result(self._core.kinetic_energy(), "kinetic_energy")

    def forces(self) -> np.ndarray:
        """(n, d) forces [N] = -d(elastic + gravity potential)/dx at x, fixed vertices included."""
        return finite_result(self._core.forces(), "forces")

    def hessian(self, project=False) -> sp.csr_matrix:
        """d^2 E_elastic/dx^2 at x as a (n d, n d) CSR matrix (dof i*d + r); ``project`` applies
        the per-element definiteness fix."""
        indptr, indices, data = self._core.hessian(bool(project))
        n = indptr.shape[0] - 1
        return sp.csr_matrix((data, indices, indptr), shape=(n, n))


def _cells(n, d, name):
    if np.ndim(n) == 0:
        n = (n,) * d
    try:
        n = tuple(positive_int(v, name) for v in n)
    except TypeError:
        raise ValueError(f"{name}: expected an int or {d} ints, got {n!r}") from None
    if len(n) != d:
        raise ValueError(f"{name}: expected an int or {d} ints, got {n}")
    cells = math.prod(n)
    if cells > _MAX_MESH_CELLS:
        raise ValueError(f"{name}: {n} is {cells} cells, more than the {_MAX_MESH_CELLS} a generated mesh "
                         "supports (its int64 element array alone would need "
                         f"{cells * 6 * (d + 1) * 8 / 2**30:.3g} GiB)")
    return n


_MAX_COORDINATE = 1e100
# 2^26 cells: up to 4e8 tetrahedra, far beyond what one Body can step, within int32 vertex ids.
_MAX_MESH_CELLS = 2**26


def _corners(lower, upper, d):
    lo = as_float_array(lower, "lower", ndim=1)
    hi = as_float_array(upper, "upper", ndim=1)
    if lo.shape != (d,) or hi.shape != (d,):
        raise ValueError(f"lower, upper: expected {d} coordinates each, got {lo.shape}, {hi.shape}")
    if not (hi > lo).all():
        raise ValueError(f"upper: expected upper > lower componentwise, got {hi} and {lo}")
    if max(np.abs(lo).max(), np.abs(hi).max()) > _MAX_COORDINATE:
        raise ValueError(f"lower, upper: coordinates beyond {_MAX_COORDINATE:g} ({lo}, {hi}); element "
                         "volumes (d-th powers of lengths) would overflow: choose other units")
    return lo, hi


def _orient(vertices, elements):
    """Swaps the last two vertices of negatively oriented elements."""
    d = vertices.shape[1]
    Ds = np.stack([vertices[elements[:, a + 1]] - vertices[elements[:, 0]] for a in range(d)], -1)
    neg = np.linalg.det(Ds) < 0
    elements[neg, -2], elements[neg, -1] = elements[neg, -1].copy(), elements[neg, -2].copy()
    return elements


def rectangle_mesh(lower, upper, n):
    """Triangles on [lower, upper] (2 coordinates each) with n cells per axis (int or (nx, ny)),
    each cell split into 2 positively oriented triangles. Returns (vertices (N, 2), elements (M, 3));
    vertex (i, j) has index i * (ny + 1) + j."""
    lo, hi = _corners(lower, upper, 2)
    nx, ny = _cells(n, 2, "n")
    I, J = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij")
    vertices = np.stack([lo[0] + (hi[0] - lo[0]) * I.ravel() / nx,
                         lo[1] + (hi[1] - lo[1]) * J.ravel() / ny], axis=1)
    vid = lambda i, j: i * (ny + 1) + j  # noqa: E731
    ci, cj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    ci, cj = ci.ravel(), cj.ravel()
    a, b, c, e = vid(ci, cj), vid(ci + 1, cj), vid(ci + 1, cj + 1), vid(ci, cj + 1)
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, e], 1)])
    return vertices, np.ascontiguousarray(_orient(vertices, tri), dtype=np.int64)


# Corners of a cube cell as (dx, dy, dz) bits; tetrahedra of the 5- and 6-tet splits.
_FIVE_EVEN = [((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)), ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)),
              ((1, 1, 0), (1, 0, 0), (0, 1, 0), (1, 1, 1)), ((1, 0, 1), (1, 0, 0), (0, 0, 1), (1, 1, 1)),
              ((0, 1, 1), (0, 1, 0), (0, 0, 1), (1, 1, 1))]
_FIVE_ODD = [((0, 0, 0), (1, 1, 0), (1, 0, 1), (0, 1, 1)), ((1, 0, 0), (0, 0, 0), (1, 1, 0), (1, 0, 1)),
             ((0, 1, 0), (0, 0, 0), (1, 1, 0), (0, 1, 1)), ((0, 0, 1), (0, 0, 0), (1, 0, 1), (0, 1, 1)),
             ((1, 1, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1))]


def _six():
    from itertools import permutations
    tets = []
    for p in permutations(range(3)):
        path, cur = [(0, 0, 0)], [0, 0, 0]
        for axis in p:
            cur[axis] = 1
            path.append(tuple(cur))
        tets.append(tuple(path))
    return tets


def box_mesh(lower, upper, n, *, tets_per_cell=6):
    """Tetrahedra on the box [lower, upper] with n cells per axis (int or (nx, ny, nz)), each
    cell split into 6 (Freudenthal/Kuhn, all cells alike) or 5 (alternating by cell parity)
    positively oriented tetrahedra. Returns (vertices (N, 3), elements (M, 4)); vertex (i, j, k)
    has index (i * (ny + 1) + j) * (nz + 1) + k."""
    lo, hi = _corners(lower, upper, 3)
    nx, ny, nz = _cells(n, 3, "n")
    if tets_per_cell not in (5, 6):
        raise ValueError(f"tets_per_cell: expected 5 or 6, got {tets_per_cell!r}")
    I, J, K = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    vertices = np.stack([lo[0] + (hi[0] - lo[0]) * I.ravel() / nx,
                         lo[1] + (hi[1] - lo[1]) * J.ravel() / ny,
                         lo[2] + (hi[2] - lo[2]) * K.ravel() / nz], axis=1)
    ci, cj, ck = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz),
                                                 indexing="ij"))

    def vid(corner, mask):
        return ((ci[mask] + corner[0]) * (ny + 1) + cj[mask] + corner[1]) * (nz + 1) + ck[mask] + corner[2]

    parts = []
    if tets_per_cell == 6:
        every = np.ones(ci.shape, bool)
        for tet in _six():
            parts.append(np.stack([vid(c, every) for c in tet], 1))
    else:
        even = (ci + cj + ck) % 2 == 0
        for mask, tets in ((even, _FIVE_EVEN), (~even, _FIVE_ODD)):
            for tet in tets:
                parts.append(np.stack([vid(c, mask) for c in tet], 1))
    elements = np.concatenate(parts)
    return vertices, np.ascontiguousarray(_orient(vertices, elements), dtype=np.int64)
