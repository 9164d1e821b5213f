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

Stability of the symplectic step: its true limit for the linearisation at rest is the root of
h^2 omega_max^2 = 4 + 2 h c, omega_max^2 the largest eigenvalue of M^-1 K at rest (2 / omega_max
undamped; the mass damping c is applied implicitly and raises it). A step above ``Body.explicit_dt_limit`` (omega_max^2
bounded above by Gershgorin: conservative, 1.4-1.75x the true omega_max^2 on triangle meshes
and 1.45-2.3x on tetrahedra (rectangle_mesh, box_mesh), so it warns on stable steps up to
1.32x or 1.52x the limit) warns once per ``step`` call with a
RuntimeWarning naming dt and the limit; a step above ``Body.unstable_dt`` (from the largest
diagonal entry K_qq / m_q, a lower bound of omega_max^2: every such step is unstable) raises
ValueError before stepping.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp

from kinema import _core
from kinema._checks import (
    as_float_array, checked_state, choice, finite, finite_result, gravity_vector, indices,
    integer, positive, positive_int, real, simulation_object, user_stacklevel)
from kinema._state import state_property
from kinema.contact import Scene  # several bodies (fem, massspring) in contact: Scene.add_body

__all__ = ["Body", "Scene", "StepStats", "MODELS", "lame", "psi", "piola", "piola_derivative",
           "rectangle_mesh", "box_mesh"]

MODELS = ("linear", "stvk", "corotated", "neohookean")
_SOLVERS = ("cholmod", "cholmod_direct", "cholmod_pcg", "cg")
_DEFINITENESS = ("adaptive", "project", "none")
_INTEGRATORS = ("implicit", "symplectic")

#: Statistics of one step or static solve (a C++ record): ``iterations`` (Newton),
#: ``converged``, ``gradient_norm`` (||grad g|| at every iterate, absolute: [kg m] for a step,
#: [N] static), ``step_length`` (accepted line-search steps), ``projected_elements`` (elements
#: whose dP/dF was clamped in the last iteration), ``cg_iterations``, ``factorizations``
#: (CHOLMOD numeric factorisations), ``seconds_assembly``, ``seconds_factor``, ``seconds_solve``,
#: ``seconds_line_search``, and the fields every method shares: ``time`` [s] after the step,
#: ``dt`` [s], ``seconds`` (wall time). ``residual`` is ||grad|| / ||grad_0|| at the end.
StepStats = _core.fem.StepStats


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


def _per_element(value, name, m):
    """A scalar parameter as a float, or one value per element as an (m,) array (values are
    checked in C++)."""
    if np.ndim(value) == 0:
        return real(value, name)
    a = as_float_array(value, name, ndim=1, finite=False)
    if a.shape != (m,):
        raise ValueError(f"{name}: expected a scalar or shape ({m},) (one per element), got {a.shape}")
    return a.copy()


_STEP_OPTIONS = ("integrator", "tol", "max_newton", "linear_solver", "cg_tol", "definiteness")
_FACTOR_KEYS = ("factor_x", "factor_weight", "factor_scale", "factor_projected", "refactor_pending")


@simulation_object
class Body:
    """An elastic body of linear triangles (2D, plane strain) or tetrahedra (3D).

    vertices: (n, d) rest positions [m]; elements: (m, d + 1) vertex indices, positively
        oriented (degenerate or inverted rest elements raise ValueError naming the element, as
        do two elements on the same vertex set, which would double its mass and stiffness).
    model: one of MODELS; youngs_modulus [Pa] and poisson_ratio in (-1, 0.5): scalars or one
        value per element (m,); density [kg/m^d]. A stiffness or mass beyond float64 raises
        ValueError naming them, as does an implicit step whose dt^2 K / M exceeds 1/eps (4.5e15)
        while the fixed vertices leave a rigid motion free (lost to rounding). K / M there is
        ``4 / explicit_dt_limit**2``, Gershgorin's upper bound of the largest eigenvalue of
        M^-1 K at rest: 1.4-1.75x the true one on triangle meshes and 1.45-2.3x on tetrahedra
        (rectangle_mesh, box_mesh, nu in [0, 0.45]), so the refusal begins at a true
        dt^2 omega_max^2 of about 2.6e15-3.2e15 (2D) or 2e15-3e15 (3D). Just below it a free body's fall under gravity already carries
        relative rounding errors of 1-7% (of order dt^2 omega_max^2 eps).
    fixed: vertex indices held in place; gravity: (d,) [m/s^2] or None (no gravity);
        damping: c [1/s], mass-proportional.
    orient: re-orient negatively oriented elements (by :func:`kinema.mesh.orient`) instead of
        refusing them; ``flipped`` then lists the indices of the elements swapped. Flat
        elements (slivers) are still refused: remove them with :func:`kinema.mesh.clean`.

    Attributes: x (n, d) [m] and v (n, d) [m/s] are writable zero-copy views of the body's
    state (valid as long as the body); rest (n, d) [m] is a copy of the rest shape;
    mass (n,) [kg] the lumped vertex masses; time [s].
    ``parameters`` names what km.diff can differentiate (:mod:`kinema.diff`).
    """

    parameters = ("youngs_modulus", "poisson_ratio", "density", "damping")

    def __init__(self, vertices, elements, *, model="neohookean", youngs_modulus, poisson_ratio,
                 density, fixed=(), gravity=None, damping=0.0, orient=False):
        vertices = as_float_array(vertices, "vertices", ndim=2)
        n, d = vertices.shape
        if d not in (2, 3):
            raise ValueError(f"vertices: expected shape (n, 2) or (n, 3), got {vertices.shape}")
        elements = indices(elements, "elements", n, (d + 1,))
        if elements.shape[0] == 0:
            raise ValueError("elements: expected at least one element")
        choice(model, "model", MODELS)
        fixed = indices(np.asarray(fixed).ravel() if np.size(fixed) else np.zeros(0, np.int64),
                        "fixed", n)
        self.flipped = np.zeros(0, np.int64)
        if orient:
            from kinema import mesh

            elements, self.flipped = mesh.orient(vertices, elements)
        m = elements.shape[0]
        self._vertices = vertices
        self._values = {"youngs_modulus": _per_element(youngs_modulus, "youngs_modulus", m),
                        "poisson_ratio": _per_element(poisson_ratio, "poisson_ratio", m),
                        "density": real(density, "density"), "damping": real(damping, "damping")}
        self._gravity = gravity_vector(gravity, d)
        self.elements = elements
        self.model = model
        self.fixed = fixed
        self._config = _core.fem.Config()
        self._config_key = None
        try:
            self._build()
        except ValueError as exc:
            hint = {"inverted": "; or pass orient=True (km.mesh.orient) to re-orient such elements",
                    "degenerate": "; km.mesh.clean(vertices, elements) removes flat elements (slivers) "
                                  "and says which"}
            for word, extra in hint.items():
                if word in str(exc):
                    raise type(exc)(f"{exc}{extra}") from None
            raise
        self._state = self._model.initial_state()
        self.contact = None  # km.contact.BodyContact once a collider is added

    def add_collider(self, shape, **options):
        """A collider (plane, box, sphere, mesh; static or moving) this body cannot pass:
        implicit steps solve contact by IPC, symplectic steps project. See
        :meth:`kinema.contact.BodyContact.add_collider`."""
        from kinema import contact

        return contact.attach(self).add_collider(shape, **options)

    def _build(self):
        """(Re)builds the C++ model and solver from the current parameter values."""
        p = _core.fem.Parameters()
        p.material = _core.fem.Material.__members__[self.model]
        p.youngs_modulus = np.atleast_1d(self._values["youngs_modulus"]).tolist()
        p.poisson_ratio = np.atleast_1d(self._values["poisson_ratio"]).tolist()
        p.density = self._values["density"]
        p.damping = self._values["damping"]
        p.gravity = self._gravity
        model = _core.fem.Model(self._vertices, self.elements, p, self.fixed)
        self._solver = _core.fem.Solver(model, self._config)
        self._model = model
        self._unstable_dt = None  # of these parameters: computed when first asked for

    def _flat_shape(self):
        return (self._model.vertex_count, self._model.dim)

    x = state_property(lambda self: self._state.x.reshape(self._flat_shape()), "x",
                       "(n, d) positions [m] (assigning copies in)")
    v = state_property(lambda self: self._state.v.reshape(self._flat_shape()), "v",
                       "(n, d) velocities [m/s] (assigning copies in)")
    rest = property(lambda self: self._model.rest, doc="(n, d) rest positions [m] (a copy).")
    mass = property(lambda self: self._model.mass, doc="(n,) lumped vertex masses [kg].")
    volume = property(lambda self: self._model.volume, doc="(m,) rest element volumes [m^d].")
    time = property(lambda self: self._state.time, doc="Simulated time [s].")

    @property
    def mu(self):
        """Lame's mu [Pa]: a float for a uniform body, else (m,) per element."""
        mu = self._model.mu
        return float(mu[0]) if np.ndim(self._values["youngs_modulus"]) == 0 and \
            np.ndim(self._values["poisson_ratio"]) == 0 else mu

    @property
    def lam(self):
        """Lame's lambda [Pa]: a float for a uniform body, else (m,) per element."""
        lam = self._model.lam
        return float(lam[0]) if np.ndim(self._values["youngs_modulus"]) == 0 and \
            np.ndim(self._values["poisson_ratio"]) == 0 else lam

    @property
    def explicit_dt_limit(self) -> float:
        """2 / omega_max [s], omega_max^2 bounded by Gershgorin on M^-1 K at rest: a conservative
        limit of the symplectic step. Computed in C++ when the solver is built (again when a
        parameter changes), so each step's check only reads it."""
        return self._solver.explicit_dt_limit

    @property
    def unstable_dt(self) -> float:
        """An upper bound [s] of the symplectic step's true limit: the root of h^2 w^2 = 4 + 2 h c
        (2 / w undamped) with w^2 = max_q K_qq / m_q over the free degrees of freedom q, K the
        elastic Hessian at rest (the Rayleigh quotient of the unit vector e_q, a lower bound of
        omega_max^2) and c the mass damping. ``inf`` when nothing is stiff. A symplectic step
        above it raises ValueError. Computed when first asked for and kept until a parameter
        changes (a parameter set through km.diff or km.torch rebuilds the solver)."""
        if self._unstable_dt is not None:
            return self._unstable_dt
        indptr, idx, data = self._solver.hessian(self._model.initial_state(), False)
        n = indptr.shape[0] - 1
        diag = sp.csr_matrix((data, idx, indptr), shape=(n, n)).diagonal()
        d = self._model.dim
        free = np.ones(n // d, bool)
        free[self.fixed] = False
        with np.errstate(over="ignore", invalid="ignore"):
            w2 = (diag.reshape(-1, d) / self.mass[:, None])[free]
        top = float(w2.max()) if w2.size else 0.0
        c = self._values["damping"]
        value = (c + math.sqrt(c * c + 4 * top)) / top if top > 0 else math.inf
        self._unstable_dt = value
        return value

    def _check_explicit_dt(self, dt, integrator):
        """RuntimeWarning above explicit_dt_limit, ValueError above unstable_dt (module docstring)."""
        if integrator != "symplectic":
            return
        limit = self.explicit_dt_limit
        if not dt > limit:
            return
        bound = self.unstable_dt
        if not dt <= bound:
            raise ValueError(f"dt: {dt:.4g} s is beyond {bound:.4g} s (unstable_dt), above which every "
                             f"symplectic step of this body is unstable (the conservative limit is "
                             f"explicit_dt_limit = {limit:.4g} s); reduce dt or use integrator='implicit'")
        warnings.warn(f"dt: {dt:.4g} s exceeds explicit_dt_limit = {limit:.4g} s (Gershgorin's conservative "
                      f"bound on the symplectic step's stability limit, which lies between it and "
                      f"{bound:.4g} s); the run may diverge: reduce dt or use integrator='implicit'",
                      RuntimeWarning, stacklevel=user_stacklevel())

    def _configure(self, integrator="implicit", tol=1e-6, max_newton=50, linear_solver="cholmod",
                   cg_tol=1e-4, definiteness="adaptive"):
        """Sets the solver's Config from step options (names converted here, values checked in
        C++ at the step)."""
        key = (integrator, tol, max_newton, linear_solver, cg_tol, definiteness)
        if key == self._config_key:
            return
        c = _core.fem.Config()
        c.integrator = _core.fem.Integrator.__members__[choice(integrator, "integrator", _INTEGRATORS)]
        c.tol = real(tol, "tol")
        c.max_newton = integer(max_newton, "max_newton")
        c.linear_solver = _core.LinearSolver.__members__[choice(linear_solver, "linear_solver", _SOLVERS)]
        c.cg_tol = real(cg_tol, "cg_tol")
        c.definiteness = _core.fem.Definiteness.__members__[choice(definiteness, "definiteness",
                                                                   _DEFINITENESS)]
        self._solver.config = c
        self._config, self._config_key = c, key

    def step(self, dt, integrator="implicit", tol=1e-6, max_newton=50, linear_solver="cholmod",
             *, cg_tol=1e-4, definiteness="adaptive", steps=1):
        """Advances ``steps`` steps of ``dt`` [s]; returns the StepStats of the last one.

        implicit: backward Euler by projected Newton (see the module docstring). Raises
        km.ConvergenceError when Newton does not reach ``tol`` in ``max_newton`` iterations
        (the state is then left at the last completed step).
        symplectic: explicit (stable below :attr:`explicit_dt_limit`, a conservative bound: a
        larger dt warns once per call with a RuntimeWarning, one above :attr:`unstable_dt` raises
        ValueError before stepping; a diverging run raises km.DivergenceError).
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
        CG to cg_tol). The lagged factor is part of :meth:`state`, so a resumed run is
        bitwise the same.
        """
        steps = positive_int(steps, "steps")
        return self._step(dt, None, steps, integrator=integrator, tol=tol, max_newton=max_newton,
                          linear_solver=linear_solver, cg_tol=cg_tol, definiteness=definiteness)

    def _step(self, dt, control, steps=1, check=True, **options):
        """The steps of ``step``; ``check=False``: without the explicit limit's check (made once
        per call by the caller: km.contact's projected steps)."""
        if self.contact is not None and self.contact.colliders and control is None:
            # km.contact checks the explicit limit once for the call
            return self.contact.step(dt, options.get("integrator", "implicit"), steps)
        if check:
            self._check_explicit_dt(real(dt, "dt"), options.get("integrator", "implicit"))
        self._configure(**options)
        dt = real(dt, "dt")
        stats = None
        for _ in range(steps):
            stats = self._solver.step(self._state, dt, control)
        return stats

    def solve_static(self, tol=1e-8, max_iter=100, load_steps=1, *, linear_solver="cholmod",
                     definiteness="adaptive"):
        """Static equilibrium under gravity and the fixed vertices, from the current x, by
        projected Newton with gravity ramped over ``load_steps``; sets x and v = 0.
        Returns a StepStats (iterations summed over load steps)."""
        self._configure(tol=tol, max_newton=max_iter, linear_solver=linear_solver,
                        definiteness=definiteness)
        return self._solver.solve_static(self._state, integer(load_steps, "load_steps"))

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        """Copies of everything that evolves: x (n, d) [m], v (n, d) [m/s], time [s], steps,
        and the record of the lagged CHOLMOD factor (``factor_*``, ``refactor_pending``) that
        the next implicit step preconditions with."""
        s = self._state
        return {"x": self.x.copy(), "v": self.v.copy(), "time": np.array(s.time),
                "steps": np.array(s.step), "factor_x": s.factor_x.reshape(-1, self._model.dim),
                "factor_weight": np.array(s.factor_weight), "factor_scale": np.array(s.factor_scale),
                "factor_projected": np.array(s.factor_projected),
                "refactor_pending": np.array(s.refactor_pending)}

    def set_state(self, state: dict) -> None:
        """Restores a :meth:`state` exactly (the resumed run is bitwise the uninterrupted one).
        A dict without the ``factor_*`` entries restores x, v, time and steps and lets the next
        implicit step factorise afresh. A refused dict changes nothing."""
        x, v, time, steps = checked_state(state, ("x", "v"), self.x.shape)
        factor = None
        if any(k in state for k in _FACTOR_KEYS):
            missing = [k for k in _FACTOR_KEYS if k not in state]
            if missing:
                raise ValueError(f"state: missing {missing[0]!r}")
            fx = as_float_array(state["factor_x"], "state['factor_x']")
            if fx.size not in (0, x.size):
                raise ValueError(f"state['factor_x']: expected shape {x.shape} or empty, got {fx.shape}")
            factor = (fx.ravel(), finite(state["factor_weight"], "state['factor_weight']"),
                      finite(state["factor_scale"], "state['factor_scale']"),
                      bool(state["factor_projected"]), bool(state["refactor_pending"]))
        s = self._state
        self.x[...] = x
        self.v[...] = v
        s.time, s.step = time, steps
        fx, w, sc, proj, pending = factor or (np.zeros(0), 0.0, 0.0, False, False)
        s.factor_x, s.factor_weight, s.factor_scale = np.ascontiguousarray(fx), w, sc
        s.factor_projected, s.refactor_pending = proj, pending

    # ------------------------------------------------------------------ energies
    def energy(self) -> float:
        """Kinetic + elastic + gravitational energy [J] (per unit thickness in 2D)."""
        c, s = self._solver, self._state
        return finite_result(c.kinetic_energy(s) + c.elastic_energy(s) + c.gravity_energy(s), "energy")

    def elastic_energy(self) -> float:
        return finite_result(self._solver.elastic_energy(self._state), "elastic_energy")

    def kinetic_energy(self) -> float:
        return finite_result(self._solver.kinetic_energy(self._state), "kinetic_energy")

    def forces(self) -> np.ndarray:
        """(n, d) forces [N] = -d(elastic + gravity potential)/dx at x, fixed vertices included."""
        return finite_result(self._solver.forces(self._state), "forces")

    def hessian(self, project=False) -> sp.csr_matrix:
        """d^2 E_elastic/dx^2 at x as a (n d, n d) CSR matrix (dof i*d + r); ``project`` applies
        the per-element definiteness fix."""
        indptr, idx, data = self._solver.hessian(self._state, bool(project))
        n = indptr.shape[0] - 1
        return sp.csr_matrix((data, idx, indptr), shape=(n, n))

    # ------------------------------------------------------------------ km.diff protocol
    _diff_state_names = ("x", "v")

    def _diff_check(self, wrt, step_options):
        if self.contact is not None and self.contact.colliders:
            raise ValueError("sim: a km.fem.Body with colliders is not differentiable (km.contact has no adjoint)")
        for key, value in step_options.items():
            if key == "steps":
                if value != 1:
                    raise ValueError(f"steps: km.diff takes one step per call; got steps={value!r} "
                                     "(use the rollout's steps instead)")
            elif key not in _STEP_OPTIONS:
                raise ValueError(f"{key}: not an option of km.fem.Body.step (expected one of "
                                 f"{', '.join(_STEP_OPTIONS)})")
        options = {k: v for k, v in step_options.items() if k != "steps"}
        self._configure(**options)
        known = (*self._diff_state_names, *self.parameters, "controls")
        for name in wrt:
            if name not in known:
                raise ValueError(f"wrt: {name!r} is not differentiable for km.fem.Body (expected "
                                 f"one of {', '.join(known)})")

    def _diff_control_shape(self):
        return self._flat_shape()

    def _diff_get(self, name):
        if name in ("x", "v"):
            return getattr(self, name).copy()
        if name in self.parameters:
            value = self._values[name]
            return value.copy() if isinstance(value, np.ndarray) else value
        raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.fem.Body")

    def _diff_set(self, name, value):
        if name in ("x", "v"):
            setattr(self, name, value)
            return
        if name not in self.parameters:
            raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.fem.Body")
        old = self._values[name]
        if name in ("youngs_modulus", "poisson_ratio"):
            value = _per_element(value, name, self.elements.shape[0])
        else:
            value = real(value, name)
        self._values[name] = value
        try:
            self._build()
        except ValueError:
            self._values[name] = old
            raise

    def _diff_step(self, dt, control, step_options):
        options = {k: v for k, v in step_options.items() if k != "steps"}
        if control is not None:
            control = np.ascontiguousarray(control, dtype=np.float64).reshape(-1)
        self._step(dt, control, **options)

    def _diff_want(self, names):
        """km.diff's parameter mask: the adjoint steps compute the gradients of ``names`` only
        (None: all of ``parameters``), skipping the element work the others cost."""
        self._diff_wanted = None if names is None else tuple(n for n in names if n in self.parameters)

    def _diff_step_adjoint(self, dt, before, after, control, grad_after, step_options):
        options = {k: v for k, v in step_options.items() if k != "steps"}
        self._configure(**options)

        def core_state(s):
            c = self._model.initial_state()
            c.x = np.ascontiguousarray(s["x"], dtype=np.float64).reshape(-1)
            c.v = np.ascontiguousarray(s["v"], dtype=np.float64).reshape(-1)
            c.time, c.step = float(s["time"]), int(s["steps"])
            if "factor_x" in s:
                # The lagged factor's record: the adjoint solve preconditions with that factor
                # (without it, every adjoint step would factorise the Hessian afresh).
                c.factor_x = np.ascontiguousarray(s["factor_x"], dtype=np.float64).reshape(-1)
                c.factor_weight, c.factor_scale = float(s["factor_weight"]), float(s["factor_scale"])
                c.factor_projected = bool(s["factor_projected"])
                c.refactor_pending = bool(s["refactor_pending"])
            return c

        flat = lambda a: np.ascontiguousarray(a, dtype=np.float64).reshape(-1)  # noqa: E731
        u = None if control is None else flat(control)
        wanted = getattr(self, "_diff_wanted", None)
        wanted = self.parameters if wanted is None else wanted
        gx, gv, gp, gu = self._solver.step_adjoint(core_state(before), core_state(after), real(dt, "dt"),
                                                   u, flat(grad_after["x"]), flat(grad_after["v"]),
                                                   list(wanted))
        return {"x": gx, "v": gv}, self._parameter_gradients(gp, wanted), gu

    def _parameter_gradients(self, gp, wanted):
        """The wanted entries of a C++ ParameterGradient (a uniform value's gradient comes summed
        over the elements in C++, as a (1,) array: a float here)."""
        params = {}
        for name in ("youngs_modulus", "poisson_ratio"):
            if name in wanted:
                g = np.array(getattr(gp, name))
                params[name] = float(g[0]) if np.ndim(self._values[name]) == 0 else g
        for name in ("density", "damping"):
            if name in wanted:
                params[name] = float(getattr(gp, name))
        return params

    def _diff_record(self, dt, steps, controls, step_options):
        """km.diff's path for a run stored whole: the steps and, later, their adjoints in one C++
        call each (no Python per step). The same states and gradients as the step-by-step path,
        bit for bit."""
        options = {k: v for k, v in step_options.items() if k != "steps"}
        self._configure(**options)
        self._check_explicit_dt(real(dt, "dt"), options.get("integrator", "implicit"))
        u = None if controls is None else np.ascontiguousarray(controls, dtype=np.float64).reshape(-1)
        run = self._solver.record(self._state, real(dt, "dt"), steps, u)
        return _Record(self, run, u, options)


class _Record:
    """A run kept by km.fem for km.diff (Body._diff_record): its states live in C++."""

    def __init__(self, body, run, controls, options):
        self._body, self._run, self._controls, self._options = body, run, controls, options

    def backward(self, grad_after, params):
        body = self._body
        body._configure(**self._options)
        flat = lambda a: np.ascontiguousarray(a, dtype=np.float64).reshape(-1)  # noqa: E731
        gx, gv, gp, gu = body._solver.run_adjoint(self._run, self._controls, flat(grad_after["x"]),
                                                  flat(grad_after["v"]), list(params))
        return {"x": gx, "v": gv}, body._parameter_gradients(gp, params), gu


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
