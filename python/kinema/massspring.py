"""km.massspring: mass-spring systems (cloth, ropes, lattices) in 2D and 3D.

Hooke springs ``U = k/2 (|x_j - x_i| - L)^2`` with per-spring stiffness ``k`` [N/m], rest length
``L`` [m] and damping along the spring ``c`` [N s/m], lumped vertex masses [kg], fixed vertices
and gravity. Integrators (``System.step``):

- ``"explicit"``: explicit Euler, x' = x + h v, v' = v + h M^-1 f (energy grows; for teaching);
- ``"symplectic"``: symplectic Euler, v' = v + h M^-1 f, x' = x + h v' (bounded energy below the
  stability limit ``System.explicit_dt_limit``);
- ``"implicit"``: [M - h C - beta h^2 K] v' = M v + h f, x' = x + h v' with the exact spring
  Jacobian K = df/dx and damping Jacobian C = df/dv (Baraff & Witkin, SIGGRAPH 1998), solved
  with CHOLMOD: by default (``linear_solver="cholmod"``, also accepted as "cholmod_pcg") PCG to
  ``cg_tol`` from v' = v, preconditioned by the CHOLMOD factorisation of an earlier step and
  refactorised when PCG needs more than 25 iterations; ``"cholmod_direct"`` factorises every
  step (symbolic analysis reused); ``"cg"`` is Jacobi-preconditioned CG. beta = 1 is
  backward Euler, 0.5 trapezoid-like. When the exact matrix is not positive definite (springs
  compressed far below rest length) the transverse term of compressed springs is clamped
  (Choi & Ko 2002) and the step's info reports ``clamped=True``.

Stability of the explicit and symplectic steps: a step of ``dt`` above
``System.explicit_dt_limit`` (2 / omega_max with omega_max^2 bounded above by Gershgorin's theorem
on M^-1 K at rest: conservative, it may refuse a stable step) warns once per ``step`` call with a
RuntimeWarning naming dt and the limit; a step above ``System.unstable_dt`` (2 / omega for a
Rayleigh quotient of M^-1 K at rest, a lower bound of omega_max: every such step is unstable, the
symplectic one grows the stiffest mode, explicit Euler's by a factor above sqrt(5) per step)
raises ValueError before stepping. The two bracket the true limit of the linearisation at rest
(damping, applied explicitly, lowers it from 2 / omega_max; ``explicit_dt_limit`` accounts for
it). Undamped explicit Euler grows energy at every dt.
Blow-ups raise km.DivergenceError naming the step and the explicit limit, never silent NaN.

Gradients (km.diff): ``System`` implements the km.diff protocol for every integrator, with
respect to the initial ``x``, ``v``, the parameters ``System.parameters`` (scalar or per item,
gradients of the same shape) and per-step vertex forces [N] (added where gravity is; fixed
vertices ignore them). The implicit step is differentiated as if its linear system were solved
exactly: one adjoint solve with the step's matrix per step, by PCG to the relative residual
``adjoint_tol`` (a km.diff step option, default 1e-12; 0 factorises every step) preconditioned
with a CHOLMOD factor lagged across the backward pass; the forward's ``cg_tol`` is not
differentiated. Where the exact Jacobian was indefinite and the step clamped it, the gradient is
that of the clamped step; zero-length springs (no force direction) contribute no gradient.
A run km.diff stores whole is stepped and reversed in C++ (``_diff_record``), bitwise the same
gradients as the step-by-step path of a checkpointed run. When such a run is let go, the System
keeps its state buffers for the next one (an optimisation loop then allocates no new memory per
rollout): up to (steps + 1) x 2 n d floats stay held until the System is.
"""

from __future__ import annotations

import warnings

import numpy as np

from kinema import _core
from kinema._checks import (
    as_float_array, choice, finite_result, gravity_vector, indices, positive, positive_int, real,
    simulation_object, spacing, user_stacklevel)
from kinema._state import assign
from kinema.errors import DivergenceError

__all__ = ["System", "Config", "StepStats", "Integrator", "cloth", "INTEGRATORS"]

INTEGRATORS = ("explicit", "symplectic", "implicit")
_SOLVERS = ("cholmod", "cholmod_direct", "cholmod_pcg", "cg")


Config = _core.massspring.Config
StepStats = _core.massspring.StepStats
Integrator = _core.massspring.Integrator
_STEP_OPTIONS = ("integrator", "beta", "linear_solver", "cg_tol")
# km.diff's step options: the step's, and the adjoint solve's tolerance (Config.adjoint_tol).
_DIFF_OPTIONS = _STEP_OPTIONS + ("adjoint_tol",)
_DEFAULTS = dict(integrator="implicit", beta=1.0, linear_solver="cholmod", cg_tol=1e-8, adjoint_tol=1e-12)


def _per_item(value, count, name):
    a = as_float_array(value, name, ndim=(0, 1))
    if np.ndim(value) == 0:  # ascontiguousarray turns a scalar into shape (1,)
        a = np.full(count, float(a[0]))
    elif a.shape != (count,):
        raise ValueError(f"{name}: expected a scalar or shape ({count},), got {a.shape}")
    return np.ascontiguousarray(a)


def _enum(value, name, enum, options):
    if isinstance(value, enum):
        return value
    return getattr(enum, choice(value, name, options))


def _implicit(config) -> bool:
    return config.integrator == Integrator.implicit


@simulation_object
class System:
    """A mass-spring system.

    x: (n, d) initial positions [m], d = 2 or 3.
    springs: (m, 2) vertex index pairs.
    stiffness: k [N/m], scalar or (m,).
    mass: vertex mass [kg], scalar or (n,).
    rest_length: L [m], scalar or (m,); default the initial distances.
    damping: c [N s/m] along each spring, scalar or (m,).
    fixed: indices of vertices held in place (their velocity stays 0; writing ``x`` moves them).
    gravity: (d,) acceleration [m/s^2], or None for no gravity.

    Attributes (writable zero-copy views of the solver's memory, valid as long as the system):
    x: (n, d) positions [m]; v: (n, d) velocities [m/s]. ``config``: the :class:`Config` of the
    last ``step`` (integrator, beta, linear_solver, cg_tol). ``parameters``: the names km.diff
    differentiates with respect to. ``fixed``, ``springs``: read-only copies of what the system
    was built with (they are fixed for its life).
    """

    parameters = ("stiffness", "rest_length", "mass", "damping")
    _diff_state_names = ("x", "v")

    def __init__(self, x, springs, *, stiffness, mass=1.0, rest_length=None, damping=0.0,
                 fixed=(), gravity=None):
        x = as_float_array(x, "x", ndim=2)
        n, d = x.shape
        if d not in (2, 3):
            raise ValueError(f"x: expected shape (n, 2) or (n, 3), got {x.shape}")
        if n < 1:
            raise ValueError("x: expected at least one vertex")
        springs = indices(springs, "springs", n, (2,))
        m = springs.shape[0]
        if m and (springs[:, 0] == springs[:, 1]).any():
            s = int(np.flatnonzero(springs[:, 0] == springs[:, 1])[0])
            raise ValueError(f"springs: spring {s} joins vertex {springs[s, 0]} to itself")
        if rest_length is None:
            rest_length = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
        given = dict(stiffness=stiffness, rest_length=rest_length, damping=damping, mass=mass)
        # Whether each parameter was given as one number: its gradient is then one number too.
        self._scalar = {k: np.ndim(v) == 0 for k, v in given.items()}
        self.fixed = indices(np.asarray(fixed).ravel() if np.size(fixed) else np.zeros(0, np.int64), "fixed", n)
        self.gravity = gravity_vector(gravity, d)
        self._core = _core.massspring.System(
            x, springs, _per_item(stiffness, m, "stiffness"), _per_item(rest_length, m, "rest_length"),
            _per_item(damping, m, "damping"), _per_item(mass, n, "mass"), self.fixed, self.gravity)
        # Copied into the C++ system: read-only copies here, so that a write cannot silently do
        # nothing (and the caller's own arrays stay writable).
        self.fixed, self.springs = self.fixed.copy(), springs.copy()
        for held in (self.fixed, self.springs):
            held.setflags(write=False)
        self.contact = None  # km.contact.BodyContact once a collider is added

    @property
    def x(self) -> np.ndarray:
        """(n, d) positions [m] (writable view; assigning copies in, shape checked)."""
        return self._core.x

    @x.setter
    def x(self, value):
        assign(self.x, value, "x")

    @property
    def v(self) -> np.ndarray:
        """(n, d) velocities [m/s] (writable view; assigning copies in, shape checked)."""
        return self._core.v

    @v.setter
    def v(self, value):
        assign(self.v, value, "v")

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._core.time

    @property
    def config(self) -> Config:
        """The step options in use (set by ``step``'s arguments)."""
        return self._core.config

    @property
    def explicit_dt_limit(self) -> float:
        """Conservative stability limit [s] of the explicit and symplectic steps: the root of
        h^2 omega^2 + 2 h gamma = 4 (symplectic Euler's limit for one mode of frequency omega
        and explicitly applied damping rate gamma; 2 / omega undamped), omega^2 and gamma bounded
        above by Gershgorin on M^-1 K at rest and M^-1 C (per vertex, the sums of 2 k / m and
        2 c / m over its springs); ``inf`` when no spring has stiffness or damping. The true
        limit lies in [explicit_dt_limit, :attr:`unstable_dt`]; undamped, with one stiffness
        and one mass throughout (and a spring between free vertices), it is at most
        sqrt(max springs at a vertex) times this. Computed in C++ once per set of parameters
        (a parameter set through km.diff or km.torch computes it anew)."""
        return self._core.explicit_dt_limit

    @property
    def unstable_dt(self) -> float:
        """An upper bound [s] of the explicit and symplectic steps' true limit 2 / omega_max:
        2 / omega with omega^2 = max over springs of the Rayleigh quotient of M^-1 K at rest for
        the spring's own stretching mode (4 k / (m_i + m_j), or k / m of the free end of a spring
        to a fixed vertex), a lower bound of omega_max^2. ``inf`` without a stiff spring to a
        free vertex. A step above it raises ValueError (see the module docstring). Cached in
        C++ as :attr:`explicit_dt_limit` is."""
        return self._core.unstable_dt

    def _check_explicit_dt(self, dt, integrator):
        """RuntimeWarning above explicit_dt_limit, ValueError above unstable_dt (module docstring)."""
        if _enum(integrator, "integrator", Integrator, INTEGRATORS) == Integrator.implicit:
            return
        limit = self._core.explicit_dt_limit
        if not dt > limit:
            return
        name = integrator if isinstance(integrator, str) else integrator.name
        bound = self._core.unstable_dt
        if not dt <= bound:
            raise ValueError(f"dt: {dt:.4g} s is beyond {bound:.4g} s (unstable_dt), above which every "
                             f"{name} step is unstable for these springs and masses (the conservative "
                             f"limit is explicit_dt_limit = {limit:.4g} s); reduce dt or use "
                             "integrator='implicit'")
        warnings.warn(f"dt: {dt:.4g} s exceeds explicit_dt_limit = {limit:.4g} s (Gershgorin's conservative "
                      f"bound on the {name} step's stability limit, which lies between it and "
                      f"{bound:.4g} s); the run may diverge: reduce dt or use integrator='implicit'",
                      RuntimeWarning, stacklevel=user_stacklevel())

    def state(self) -> dict:
        """Copies of everything that evolves: ``x``, ``v`` (n, d), ``time`` [s], ``step``, the
        branch of the last implicit step (``clamped``) and the record of the lagged CHOLMOD
        factor the next implicit step preconditions with (``factor_*``). ``set_state`` of it
        resumes the run bit for bit."""
        return self._core.state()

    def set_state(self, state: dict) -> None:
        """Restores a ``state()`` exactly (x and v are copied into the existing views)."""
        if not isinstance(state, dict):
            raise ValueError(f"state: expected a dict from System.state(), got {type(state).__name__}")
        self._core.set_state(state)

    def _configure(self, integrator, beta, linear_solver, cg_tol, adjoint_tol=None, config=None):
        c = self._core.config if config is None else config
        c.integrator = _enum(integrator, "integrator", Integrator, INTEGRATORS)
        c.linear_solver = _enum(linear_solver, "linear_solver", _core.LinearSolver, _SOLVERS)
        c.beta = real(beta, "beta")
        c.cg_tol = real(cg_tol, "cg_tol")
        if adjoint_tol is not None:
            c.adjoint_tol = real(adjoint_tol, "adjoint_tol")
        return c

    def step(self, dt, integrator="implicit", beta=1.0, *, linear_solver="cholmod",
             cg_tol=1e-8, steps=1) -> StepStats:
        """Advances ``steps`` steps of ``dt`` [s] with ``integrator``; see the module docstring.
        Returns the :class:`StepStats` summed over the steps. Explicit and symplectic steps above
        :attr:`explicit_dt_limit` warn (RuntimeWarning, once per call) and above
        :attr:`unstable_dt` raise ValueError before any step."""
        return self._step(dt, None, integrator=integrator, beta=beta, linear_solver=linear_solver,
                          cg_tol=cg_tol, steps=steps)

    def add_collider(self, shape, **options):
        """A collider (plane, box, sphere, mesh; static or moving) that this system's vertices
        (and its ``triangles``, see :func:`kinema.contact.attach`) cannot pass: implicit steps
        solve contact by IPC, symplectic steps project. See :meth:`kinema.contact.BodyContact.add_collider`."""
        from kinema import contact

        return contact.attach(self).add_collider(shape, **options)

    def _step(self, dt, control, *, integrator="implicit", beta=1.0, linear_solver="cholmod",
              cg_tol=1e-8, steps=1, check=True):
        """The steps of ``step``; ``check=False``: without the explicit limit's check (made once
        per call by the caller: km.contact's projected steps)."""
        if self.contact is not None and self.contact.colliders and control is None:
            # km.contact checks the explicit limit once for the call
            return self.contact.step(dt, integrator, positive_int(steps, "steps"), beta=beta)
        dt = positive(dt, "dt")  # before the checks: -1e308 is a bad dt, not a lost mass term
        if check:
            self._check_explicit_dt(dt, integrator)
        self._configure(integrator, beta, linear_solver, cg_tol)
        try:
            return self._core.step(dt, positive_int(steps, "steps"), control)
        except (ValueError, DivergenceError) as exc:
            # The error paths only: a NaN/Inf written into the x or v view is the cause to name
            # (not dt); a matrix whose dt^2 K / M exceeds 1/eps has lost its mass term (and the
            # rigid motions it alone holds) to rounding: not an indefinite matrix.
            for name in ("x", "v"):
                bad = ~np.isfinite(getattr(self._core, name))
                if bad.any():
                    raise ValueError(f"{name}: holds {int(bad.sum())} non-finite value(s) (first at vertex "
                                     f"{int(np.flatnonzero(bad.any(axis=1))[0])}), written through the "
                                     "view or left by a diverged run") from None
            if isinstance(exc, DivergenceError):
                raise
            ratio = dt * dt * self._core.gershgorin_omega2  # inf, not OverflowError, past 1e154
            if _implicit(self._core.config) and ratio > 1 / np.finfo(float).eps:
                raise ValueError(f"stiffness, dt: dt^2 K / M reaches {ratio:.3g} (Gershgorin), beyond the "
                                 "4.5e15 float64 resolves: the mass term is lost to rounding; reduce dt or "
                                 "the stiffness, or choose other units") from None
            if not str(exc).startswith("A:"):
                raise
            # the implicit matrix M - h C - beta h^2 K overflowed: dt is the argument to blame
            raise ValueError(f"dt: {dt} makes the implicit matrix M - dt C - beta dt^2 K non-finite "
                             f"({exc}); use a smaller dt") from None

    def energy(self) -> float:
        """Kinetic + spring + gravitational energy [J] (gravity potential -m g . x)."""
        c = self._core
        return finite_result(c.kinetic_energy() + c.spring_energy() + c.gravity_energy(), "energy")

    def kinetic_energy(self) -> float:
        return finite_result(self._core.kinetic_energy(), "kinetic_energy")

    def spring_energy(self) -> float:
        return finite_result(self._core.spring_energy(), "spring_energy")

    def forces(self) -> np.ndarray:
        """(n, d) total force [N] at the current state: springs, damping and gravity."""
        return finite_result(self._core.forces(), "forces")

    # ------------------------------------------------------------ km.diff protocol

    def _diff_check(self, wrt, step_options):
        if self.contact is not None and self.contact.colliders:
            raise ValueError("sim: a km.massspring.System with colliders is not differentiable (km.contact has no adjoint)")
        for key in step_options:
            if key not in _DIFF_OPTIONS:
                raise ValueError(f"{key}: not an option of km.massspring.System under km.diff "
                                 f"(expected {', '.join(_DIFF_OPTIONS)}; km.diff takes one step per call)")
        _core.massspring.check_config(self._configure(**(_DEFAULTS | step_options), config=Config()))
        for name in wrt:
            if name not in self._diff_state_names + self.parameters + ("controls",):
                raise ValueError(f"wrt: {name!r} is not differentiable in km.massspring.System "
                                 f"(expected x, v, controls or one of {', '.join(self.parameters)})")

    def _diff_control_shape(self):
        return self.x.shape

    def _diff_get(self, name):
        if name in self._diff_state_names:
            return getattr(self, name).copy()
        if name in self.parameters:
            value = self._core.parameter(name)
            return float(value[0]) if self._scalar[name] and value.size else value
        raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.massspring.System")

    def _diff_set(self, name, value):
        if name in self._diff_state_names:
            setattr(self, name, value)
            return
        if name not in self.parameters:
            raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.massspring.System")
        count = len(self.springs) if name != "mass" else len(self.x)
        self._core.set_parameter(name, _per_item(value, count, name))
        self._scalar[name] = np.ndim(value) == 0

    def _diff_step(self, dt, control, step_options):
        self._step(dt, control, **{k: v for k, v in step_options.items() if k != "adjoint_tol"})

    def _diff_step_adjoint(self, dt, before, after, control, grad_after, step_options):
        self._configure(**(_DEFAULTS | step_options))
        gx, gv, params, gcontrol = self._core.step_adjoint(
            real(dt, "dt"), before, after, control, grad_after["x"], grad_after["v"])
        # Per item even for a scalar parameter: km.diff sums over the steps, then over the items,
        # as _diff_record's run does (the two agree bitwise).
        return {"x": gx, "v": gv}, params, gcontrol

    def _diff_record(self, dt, steps, controls, step_options):
        """km.diff's path for a run stored whole: the steps and their adjoints in C++."""
        options = {k: v for k, v in step_options.items() if k != "adjoint_tol"}
        self._configure(**(_DEFAULTS | options))
        dt = real(dt, "dt")
        self._check_explicit_dt(dt, options.get("integrator", "implicit"))
        try:
            trajectory = self._core.record(dt, steps, controls)
        except ValueError as exc:
            if not str(exc).startswith("A:"):
                raise
            raise ValueError(f"dt: {dt} makes the implicit matrix M - dt C - beta dt^2 K non-finite "
                             f"({exc}); use a smaller dt") from None
        return _Record(self, trajectory, step_options)


class _Record:
    """A run kept by km.massspring for km.diff (System._diff_record)."""

    def __init__(self, system, trajectory, step_options):
        self._system, self._trajectory, self._options = system, trajectory, step_options

    def backward(self, grad_after, params):
        self._system._configure(**(_DEFAULTS | self._options))
        gx, gv, grads, gcontrols = self._trajectory.backward(grad_after["x"], grad_after["v"], bool(params))
        grads = {} if grads is None else {k: grads[k] for k in params}
        return {"x": gx, "v": gv}, grads, gcontrols


class ClothMesh(tuple):
    """What :func:`cloth` returns: the pair ``(x, springs)`` (so ``x, springs = cloth(...)``
    unpacks as before), or ``(x, springs, kinds)`` with ``return_kinds=True``, with the
    attributes ``x``, ``springs``, ``kinds`` (0 structural, 1 shear, 2 bending) and
    ``triangles`` ((2 (nx-1)(ny-1), 3) vertex indices, counter-clockwise seen from the plane's
    normal, for rendering and for :func:`kinema.io.write_mesh`)."""

    def __new__(cls, x, springs, kinds, triangles, return_kinds):
        self = super().__new__(cls, (x, springs, kinds) if return_kinds else (x, springs))
        self.x, self.springs, self.kinds, self.triangles = x, springs, kinds, triangles
        return self


_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def cloth(nx, ny, size, *, dim=3, plane="xy", origin=None, return_kinds=False):
    """A rectangular cloth of nx x ny vertices with structural, shear and bending springs.

    size: side length [m] (scalar) or (sx, sy). Vertex (i, j) -> index i * ny + j at
    origin + i sx/(nx-1) e_a + j sy/(ny-1) e_b, where (a, b) are the axes of ``plane``: "xy"
    (default), "xz" (horizontal when y is up) or "yz" (3D only). origin: the position of
    vertex (0, 0) (default 0). Springs: structural (grid edges), shear (both cell diagonals),
    bending (every second vertex along each axis), in that order.
    Returns a :class:`ClothMesh`: it unpacks as (x, springs), or (x, springs, kinds) when
    return_kinds, and has ``.triangles`` (two per grid cell).

        x, springs = km.massspring.cloth(20, 20, 1.0, plane="xz", origin=(0, 1, 0))
        tris = km.massspring.cloth(20, 20, 1.0).triangles
    """
    nx = positive_int(nx, "nx")
    ny = positive_int(ny, "ny")
    if nx < 2 or ny < 2:
        raise ValueError(f"nx, ny: expected at least 2 vertices per side, got ({nx}, {ny})")
    if nx * ny > 2**26:
        raise ValueError(f"nx, ny: {nx} x {ny} vertices is more than the 2^26 a generated cloth supports")
    if dim not in (2, 3):
        raise ValueError(f"dim: expected 2 or 3, got {dim!r}")
    if plane not in _PLANES or (dim == 2 and plane != "xy"):
        allowed = ", ".join(f'"{p}"' for p in (_PLANES if dim == 3 else ["xy"]))
        raise ValueError(f"plane: expected one of {allowed} for dim={dim}, got {plane!r}")
    s = as_float_array(size, "size", ndim=(0, 1))
    if np.ndim(size) == 0:
        sx = sy = float(s[0])
    elif s.shape == (2,):
        sx, sy = float(s[0]), float(s[1])
    else:
        raise ValueError(f"size: expected a scalar or (sx, sy), got shape {s.shape}")
    spacing(sx, "size")
    spacing(sy, "size")
    I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    x = np.zeros((nx * ny, dim))
    if origin is not None:
        o = as_float_array(origin, "origin", ndim=1)
        if o.shape != (dim,):
            raise ValueError(f"origin: expected {dim} components, got shape {o.shape}")
        x[:] = o
    a, b = _PLANES[plane]
    x[:, a] += (I * sx / (nx - 1)).ravel()
    x[:, b] += (J * sy / (ny - 1)).ravel()
    idx = (I * ny + J)

    def pairs(a, b):
        return np.stack([a.ravel(), b.ravel()], axis=1)

    groups = [
        [pairs(idx[:-1, :], idx[1:, :]), pairs(idx[:, :-1], idx[:, 1:])],
        [pairs(idx[:-1, :-1], idx[1:, 1:]), pairs(idx[1:, :-1], idx[:-1, 1:])],
        [pairs(idx[:-2, :], idx[2:, :]), pairs(idx[:, :-2], idx[:, 2:])],
    ]
    springs, kinds = [], []
    for kind, group in enumerate(groups):
        for p in group:
            springs.append(p)
            kinds.append(np.full(len(p), kind, dtype=np.int64))
    springs = np.ascontiguousarray(np.concatenate(springs), dtype=np.int64)
    q = idx[:-1, :-1].ravel()
    triangles = np.ascontiguousarray(np.concatenate([np.stack([q, q + ny, q + ny + 1], 1),
                                                     np.stack([q, q + ny + 1, q + 1], 1)]), dtype=np.int64)
    return ClothMesh(x, springs, np.concatenate(kinds), triangles, return_kinds)
