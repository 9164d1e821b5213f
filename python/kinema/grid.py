"""Incompressible flow on a MAC (staggered) grid, 2D and 3D: smoke and viscous flow.

Each :meth:`Fluid.step` splits the Navier-Stokes equations (density 1, kinematic pressure) into
five phases, in order: advection of velocity and scalars (semi-Lagrangian, Stam 1999; or
MacCormack / BFECC clamped to the interpolation stencil, Selle et al. 2008), body forces
(gravity, buoyancy, vorticity confinement, Fedkiw, Stam & Jensen 2001), implicit viscosity
(backward Euler, stable for any dt), Chorin's projection (the pressure Poisson problem solved
by kinema's MGPCG, :mod:`kinema.poisson`, also on periodic domains; CG for odd periodic sizes),
and a blow-up check.
See Bridson, "Fluid Simulation for Computer Graphics" (2nd ed., 2015) for the MAC grid.

Layout: cells ``(nx, ny[, nz])`` of size ``h``; ``u`` has shape ``(nx+1, ny[, nz])`` at
``(i*h, (j+0.5)h)``, ``v`` ``(nx, ny+1[, nz])``, ``w`` ``(nx, ny, nz+1)``. In a periodic domain the
last face along each component's axis duplicates the first and is kept equal to it.

Boundaries: closed walls (free or no slip, moving lids), periodic, or open sides (``open=``:
p = 0 there, so smoke leaves the box; the pressure solve keeps its multigrid speed). Sources
(``add_source``) impose density, temperature or velocity in a region before every step: emitters
and inflows from Python, as scene files' ``source`` objects do. Example: examples/smoke_outflow.py.
"""

from __future__ import annotations

import numpy as np

from kinema import _core
from kinema._checks import (
    as_float_array, checked_state, choice, finite, finite_result, grid_shape, positive_int, real,
    simulation_object, spacing, time_step)
from kinema._state import assign
from kinema.diff import _memory_bytes

__all__ = ["Fluid", "StepInfo", "advect", "SCHEMES", "ADVECTION_KERNELS"]

SCHEMES = ("semi_lagrangian", "maccormack", "bfecc")
ADVECTION_KERNELS = ("auto", "nodes", "rows", "rows_avx2")
_PROJECTIONS = ("mgpcg", "multigrid", "cg")
_SIDES = {"x-": (0, 0), "x+": (0, 1), "y-": (1, 0), "y+": (1, 1), "z-": (2, 0), "z+": (2, 1)}


#: What one step did (kinema._core.StepStats: time, dt, seconds; and the pressure SolveInfo,
#: cfl = max|u| dt / h before the step, viscosity_iterations and per-phase advect_seconds,
#: forces_seconds, viscosity_seconds, projection_seconds).
StepInfo = _core.grid.StepStats


def _rk(rk_order):
    if isinstance(rk_order, bool) or rk_order not in (1, 2, 3):
        raise ValueError(f"rk_order: expected 1, 2 or 3, got {rk_order!r}")
    return int(rk_order)


def _internal(vector, dim):
    """A user d-vector on the solver's internal axes (a 2D grid is the 3D grid (1, nx, ny))."""
    return [0.0] * (3 - dim) + [float(x) for x in vector]


@simulation_object
class Fluid:
    """An incompressible fluid on a MAC grid of ``shape`` cells of size ``h`` [m].

    advection: "semi_lagrangian", "maccormack" or "bfecc" (the last two clamped);
    rk_order: 1, 2 or 3 (back-trace). projection: "mgpcg" (default), "multigrid" or "cg";
    tol: relative residual of the pressure solve. viscosity: kinematic nu [m^2/s] (implicit).
    pressure_vcycles: None (default: solve the pressure to tol) or k >= 1: every projection is
    exactly k multigrid V-cycles from a zero pressure (tol, max_iter unused; projection "mgpcg"
    or "multigrid"), a fixed linear map whose gradient km.diff gives exactly (the same k cycles;
    the cheap projection of a differentiable rollout, like DiffTaichi's fixed Jacobi sweeps). It is
    not converged: the divergence it leaves, ||div u after|| / ||div u before|| over the fluid
    cells, is each step's ``pressure.residual`` (about 0.1**k on a smooth flow). At most 1000.
    boundary: "closed" or "periodic"; walls: "free_slip" or "no_slip" (closed boundaries).
    gravity: a d-vector [m/s^2], or None for no gravity. density, temperature: enable the passive scalars;
    buoyancy = (alpha, beta): force (-alpha*density + beta*temperature) * up [m/s^2], up
    opposite to gravity (or +y without gravity). vorticity_confinement: epsilon >= 0.
    advection_kernel: which implementation advects, all with bitwise the same results: "auto"
    (the fastest that applies), "nodes" (node by node, every case), "rows" or "rows_avx2"
    (vectorised along rows, baseline ISA or AVX2; not with no-slip or moving walls).
    open: sides ("x-", "x+", "y-", "y+", "z-", "z+", or a tuple of them) that are open instead of
    walls: the pressure is 0 there (a Dirichlet condition of the projection) and the normal
    velocity free, so fluid and smoke leave (or are drawn in) through them; scalars and
    velocities extend the nearest value across them. Not with boundary="periodic".

    Sources (inflows, emitters): :meth:`add_source` imposes density, temperature and/or velocity
    in a region of cells before every step, in :meth:`step` and :meth:`advance` alike.

    State (writable views of the solver's memory, never reallocated; assigning to an attribute,
    ``sim.density = array``, copies into it after checking the shape):
      u, v[, w]: MAC velocities [m/s] (see the module docstring for shapes);
      pressure: (nx, ny[, nz]) kinematic pressure p/rho [m^2/s^2] of the last projection;
      solid: (nx, ny[, nz]) bool, obstacle cells (faces touching them have zero velocity;
        changes take effect at the next step);
      density, temperature: (nx, ny[, nz]) scalars, when enabled.
    """

    def __init__(self, shape, h, *, advection="maccormack", rk_order=2, projection="mgpcg", tol=1e-6,
                 viscosity=0.0, boundary="closed", walls="free_slip", gravity=None, density=False,
                 temperature=False, buoyancy=(0.0, 0.0), vorticity_confinement=0.0, max_iter=None,
                 advection_kernel="auto", open=(), pressure_vcycles=None):
        self.shape = grid_shape(shape, "shape")
        self.dim = len(self.shape)
        self.h = spacing(h, "h")
        self.advection = choice(advection, "advection", SCHEMES)
        self.rk_order = _rk(rk_order)
        self.projection = choice(projection, "projection", _PROJECTIONS)
        self.tol = real(tol, "tol")
        self.viscosity = real(viscosity, "viscosity")
        self.boundary = choice(boundary, "boundary", ("closed", "periodic"))
        self.walls = choice(walls, "walls", ("free_slip", "no_slip"))
        if gravity is None:
            g = []
        else:
            g = as_float_array(gravity, "gravity", ndim=1)
            if g.shape != (self.dim,):
                raise ValueError(f"gravity: expected {self.dim} components, got shape {g.shape}")
            g = [float(x) for x in g]
        self.gravity = tuple(g) if g else None
        for flag, name in ((density, "density"), (temperature, "temperature")):
            if not isinstance(flag, (bool, np.bool_)):
                raise ValueError(f"{name}: expected True or False, got {flag!r}")
        try:
            alpha, beta = buoyancy
        except (TypeError, ValueError):
            raise ValueError(f"buoyancy: expected a pair (alpha, beta), got {buoyancy!r}") from None
        alpha, beta = real(alpha, "buoyancy"), real(beta, "buoyancy")
        self.buoyancy = (alpha, beta)
        self.vorticity_confinement = real(vorticity_confinement, "vorticity_confinement")
        max_iter = positive_int(max_iter, "max_iter", allow_none=True) or 0
        # At about 0.1 of the divergence left per V-cycle, 40 cycles reach rounding: a count above
        # 1000 is a mistake (a 10**12 count would run for ever), and None solves to tol.
        self.pressure_vcycles = positive_int(pressure_vcycles, "pressure_vcycles", allow_none=True, high=1000)
        if self.pressure_vcycles and self.projection not in ("mgpcg", "multigrid"):
            raise ValueError(f"pressure_vcycles: fixed V-cycles run on the multigrid hierarchy; "
                             f"projection={self.projection!r} cannot be combined with them")
        self.advection_kernel = choice(advection_kernel, "advection_kernel", ADVECTION_KERNELS)
        self.open = self._sides(open)
        config = _core.grid.Config()
        config.advection = getattr(_core.grid.AdvectionScheme, self.advection)
        config.rk_order = self.rk_order
        config.advection_kernel = getattr(_core.grid.AdvectionKernel, self.advection_kernel)
        config.projection = getattr(_core.poisson.Method, self.projection)
        config.tol, config.max_iter, config.viscosity = self.tol, max_iter, self.viscosity
        config.pressure_vcycles = self.pressure_vcycles or 0
        config.periodic, config.no_slip = self.boundary == "periodic", self.walls == "no_slip"
        open_walls = [False] * 6
        for side in self.open:
            axis, s = _SIDES[side]
            open_walls[2 * (axis + 3 - self.dim) + s] = True
        config.open = open_walls
        if g:
            config.gravity = _internal(g, self.dim)
        config.density, config.temperature = bool(density), bool(temperature)
        config.alpha, config.beta = alpha, beta
        config.vorticity_confinement = self.vorticity_confinement
        self._core = _core.grid.Fluid(list(self.shape), self.h, config)

    def _sides(self, sides):
        names = tuple(s for s in _SIDES if self.dim == 3 or not s.startswith("z"))
        if isinstance(sides, str):
            sides = (sides,)
        try:
            sides = tuple(sides)
        except TypeError:
            raise ValueError(f"open: expected side names among {', '.join(names)}, got {sides!r}") from None
        for side in sides:
            choice(side, "open", names)
        if len(set(sides)) != len(sides):
            raise ValueError(f"open: a side is named twice in {sides}")
        return tuple(sorted(sides, key=names.index))

    # ------------------------------------------------------------------ state views
    @property
    def u(self):
        """(nx+1, ny[, nz]) x-velocity on the faces normal to x [m/s]."""
        return self._core.velocity(0)

    @u.setter
    def u(self, value):
        assign(self.u, value, "u")

    @property
    def v(self):
        """(nx, ny+1[, nz]) y-velocity on the faces normal to y [m/s]."""
        return self._core.velocity(1)

    @v.setter
    def v(self, value):
        assign(self.v, value, "v")

    @property
    def w(self):
        """(nx, ny, nz+1) z-velocity [m/s] (3D only)."""
        if self.dim != 3:
            raise AttributeError("w: a 2D Fluid has no z-velocity (give a 3D shape)")
        return self._core.velocity(2)

    @w.setter
    def w(self, value):
        assign(self.w, value, "w")

    @property
    def velocity(self):
        """The MAC components (u, v[, w]) as a tuple of views; assign a sequence of d arrays."""
        return tuple(self._core.velocity(c) for c in range(self.dim))

    @velocity.setter
    def velocity(self, value):
        try:
            comps = list(value) if not isinstance(value, np.ndarray) or value.dtype == object else None
        except TypeError:
            comps = None
        if comps is None or len(comps) != self.dim:
            raise ValueError(f"velocity: expected a sequence of {self.dim} MAC components (u, v[, w])")
        for c, (view, comp) in enumerate(zip(self.velocity, comps)):
            assign(view, comp, "uvw"[c])

    @property
    def pressure(self):
        """(nx, ny[, nz]) kinematic pressure [m^2/s^2] of the last projection (the next one
        starts from it when that helps)."""
        return self._core.pressure

    @pressure.setter
    def pressure(self, value):
        assign(self.pressure, value, "pressure")

    @property
    def solid(self):
        """(nx, ny[, nz]) bool obstacle cells (changes take effect at the next step)."""
        return self._core.solid

    @solid.setter
    def solid(self, mask):
        assign(self.solid, mask, "solid")

    @property
    def density(self):
        """(nx, ny[, nz]) smoke density (when enabled)."""
        q = self._core.scalar("density")
        if q is None:
            raise AttributeError("density: disabled; create the Fluid with density=True")
        return q

    @density.setter
    def density(self, value):
        assign(self.density, value, "density")

    @property
    def temperature(self):
        """(nx, ny[, nz]) temperature (when enabled)."""
        q = self._core.scalar("temperature")
        if q is None:
            raise AttributeError("temperature: disabled; create the Fluid with temperature=True")
        return q

    @temperature.setter
    def temperature(self, value):
        assign(self.temperature, value, "temperature")

    def cell_centers(self) -> np.ndarray:
        """(nx, ny[, nz], d) cell-centre coordinates [m], for building masks of regions:
        ``inside = np.linalg.norm(sim.cell_centers() - c, axis=-1) < r``."""
        axes = [(np.arange(n) + 0.5) * self.h for n in self.shape]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)

    def add_source(self, region, *, density=None, temperature=None, velocity=None) -> int:
        """Imposes values in ``region`` (a bool array of the grid's shape) before every step:
        ``density`` / ``temperature`` in its cells (the fields must be enabled), and ``velocity``
        (a d-vector [m/s]) on every face of its cells, each face taking the component normal to
        it (faces of walls and solid cells keep their zero). Sources apply in the order added, in
        :meth:`step` and in every sub-step of :meth:`advance`. An inflow: a source of velocity
        next to a closed side with an open side opposite. Returns the source's index."""
        m = np.asarray(region)
        if m.shape != self.shape or m.dtype != np.bool_:
            raise ValueError(f"region: expected a bool array of shape {self.shape}, got {m.dtype} {m.shape}")
        vel = None
        if velocity is not None:
            vel = as_float_array(velocity, "velocity", ndim=1)
            if vel.shape != (self.dim,):
                raise ValueError(f"velocity: expected {self.dim} components, got shape {vel.shape}")
            vel = [float(x) for x in vel]
        return self._core.add_source(m.astype(np.uint8), None if density is None else real(density, "density"),
                                     None if temperature is None else real(temperature, "temperature"), vel)

    def clear_sources(self) -> None:
        """Removes every source added by :meth:`add_source`."""
        self._core.clear_sources()

    @property
    def source_count(self) -> int:
        return self._core.source_count

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._core.time

    @property
    def steps(self) -> int:
        """Steps taken since the start."""
        return self._core.steps

    #: The differentiable parameters (km.diff).
    parameters = ("viscosity",)

    def _state_arrays(self):
        arrays = dict(zip("uvw", self.velocity))
        arrays["pressure"] = self.pressure
        for name in ("density", "temperature"):
            q = self._core.scalar(name)
            if q is not None:
                arrays[name] = q
        return arrays

    def state(self) -> dict:
        """Everything a step evolves, as copies: u, v[, w] [m/s], pressure [m^2/s^2] (the warm
        start of the next projection), density and temperature when enabled, time [s] and
        steps. :meth:`set_state` of this dict resumes bit for bit."""
        out = {name: view.copy() for name, view in self._state_arrays().items()}
        out["time"], out["steps"] = np.float64(self.time), np.int64(self.steps)
        return out

    def set_state(self, state) -> None:
        """Restores a :meth:`state` dict of a Fluid of the same shape and options (copies into
        the state's arrays, so views taken before stay valid). Obstacles, walls and sources are
        the model's, not the state's: they stay as set. A refused dict changes nothing."""
        arrays = self._state_arrays()
        time, steps = checked_state(state, (), None)
        values = {}
        for name, view in arrays.items():  # every entry checked before anything is restored
            if name not in state:
                raise ValueError(f"state: missing {name!r}")
            values[name] = as_float_array(state[name], f"state[{name!r}]")
            if values[name].shape != view.shape:
                raise ValueError(f"state[{name!r}]: expected shape {view.shape}, got {values[name].shape}")
        for name, view in arrays.items():
            view[...] = values[name]
        self._core.time, self._core.steps = time, steps

    # ------------------------------------------------------------------ stepping
    def step(self, dt) -> StepInfo:
        """Advances by dt [s] (any dt > 0; accuracy needs a CFL number of a few at most)."""
        return self._core.step(time_step(dt))

    # ------------------------------------------------------------ km.diff protocol
    @property
    def _diff_state_names(self):
        names = tuple("uvw"[:self.dim])
        return names + tuple(n for n in ("density", "temperature") if self._core.scalar(n) is not None)

    def _diff_check(self, wrt, step_options):
        for key in step_options:
            raise ValueError(f"{key}: km.grid.Fluid.step takes no options (km.diff passes none)")
        self._core.check_differentiable()
        names = self._diff_state_names + self.parameters + ("controls",)
        for name in wrt:
            if name not in names:
                raise ValueError(f"wrt: {name!r} is not differentiable in this km.grid.Fluid "
                                 f"(expected one of {', '.join(names)})")

    def _diff_control_shape(self):
        return self.shape + (self.dim,)

    def _diff_get(self, name):
        if name in self._diff_state_names:
            return getattr(self, name).copy()
        if name == "viscosity":
            return float(self.viscosity)
        raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.grid.Fluid")

    def _diff_set(self, name, value):
        if name in self._diff_state_names:
            setattr(self, name, value)
        elif name == "viscosity":
            self._core.set_viscosity(real(value, "viscosity"))
            self.viscosity = float(value)
        else:
            raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.grid.Fluid")

    def _diff_step(self, dt, control, step_options):
        self._core.step(time_step(dt), control)

    def _diff_step_keep(self, dt, control, step_options):
        # km.diff: a step whose adjoint comes soon; returns MacCormack's or BFECC's first
        # advection passes and clamp bounds so the adjoint reads them instead of recomputing
        # them (None for semi-Lagrangian, whose adjoint reads none)
        if self.advection == "semi_lagrangian":
            self._diff_step(dt, control, step_options)
            return None
        spent = getattr(self, "_diff_spent", None)  # ones the adjoint has read, refilled
        return self._core.step_keep(time_step(dt), control, spent.pop() if spent else None)

    def _diff_record(self, dt, steps, controls, step_options):
        """km.diff's path for a run stored whole: the steps and their adjoints in C++ (the same
        calls, so the same bits, as _diff_step and _diff_step_adjoint)."""
        # MacCormack and BFECC: each step's first advection passes and clamp bounds (3 and 4
        # arrays per advected field) are kept too, so the backward reads them instead of
        # recomputing them, where the run then still takes at most half the machine's memory
        keep = False
        if self.advection != "semi_lagrangian":
            state = self.state()
            per_state = sum(v.nbytes for v in state.values() if isinstance(v, np.ndarray))
            fields = sum(state[name].nbytes for name in self._diff_state_names)  # the advected ones
            need = (int(steps) + 1) * per_state + int(steps) * fields * (3 if self.advection == "maccormack" else 4)
            keep = need <= 0.5 * _memory_bytes()
        return _Record(self, self._core.record(time_step(dt), int(steps), controls, keep))

    def _diff_want(self, names):
        # km.diff: the parameters a backward pass wants (None: all); without the viscosity the
        # adjoint recomputes only the advection's first passes of each step
        self._diff_wanted = names
        self._diff_spent = []  # a backward's spent advection scratch goes with it
        if names is not None:  # a backward starts: its adjoint pressure solves chain from zero
            self._core.reset_adjoint_warm_start()

    def _diff_step_adjoint(self, dt, before, after, control, grad_after, step_options, forward=None):
        wanted = getattr(self, "_diff_wanted", None)
        want_nu = wanted is None or "viscosity" in wanted
        # inside km.diff's backward (wanted set) each pressure solve warm-starts from the one of
        # the step after it, the previous call of that backward; a lone call starts from zero
        grads, g_nu, g_control = self._core.step_adjoint(time_step(dt), before, control, grad_after, want_nu,
                                                         forward, wanted is not None)
        if forward is not None and wanted is not None:  # within km.diff's backward, which drops it
            spent = self._diff_spent
            if len(spent) < 2:  # km.diff holds at most two at once
                spent.append(forward)
        return grads, ({"viscosity": g_nu} if want_nu else {}), g_control

    def stable_dt(self, cfl=1.0, *, max_dt=None) -> float:
        """The CFL step cfl * h / u_max [s], at most ``max_dt``, where u_max = max|u| +
        sqrt(5 h |g|) (Bridson 2015, Sec. 3.2: the speed gravity adds in one step) also counts
        moving walls and velocity sources; ``inf`` when nothing moves and no max_dt is given."""
        return self._core.stable_dt(real(cfl, "cfl"), _max_dt(max_dt))

    def advance(self, duration, cfl=1.0, *, max_dt=None) -> int:
        """Advances by ``duration`` [s] in steps of :meth:`stable_dt`, the last one landing on the
        end; returns the step count. The last step's StepInfo is kept in ``self.last_step``."""
        steps, info = self._core.advance(real(duration, "duration"), real(cfl, "cfl"), _max_dt(max_dt))
        self.last_step = info
        return steps

    def set_wall_velocity(self, side, velocity):
        """Makes wall ``side`` ("x-", "x+", "y-", "y+", "z-", "z+") a no-slip wall moving with the
        tangential ``velocity`` (a d-vector [m/s] whose normal component must be 0). The wall
        drags the fluid through the viscosity and through advection: interpolation between the
        last velocity node and the wall runs linearly to the wall's velocity (as do all no-slip
        walls, at rest or not; free-slip walls extend the nearest value)."""
        choice(side, "side", tuple(s for s in _SIDES if self.dim == 3 or not s.startswith("z")))
        axis, s = _SIDES[side]
        vel = as_float_array(velocity, "velocity", ndim=1)
        if vel.shape != (self.dim,):
            raise ValueError(f"velocity: expected {self.dim} components, got shape {vel.shape}")
        self._core.set_wall_velocity(axis, s, [float(x) for x in vel])

    # ------------------------------------------------------------------ diagnostics
    def divergence(self):
        """(nx, ny[, nz]) discrete divergence of the MAC velocity [1/s] (0 in solid cells)."""
        return finite_result(self._core.divergence(), "divergence")

    def velocity_at(self, points):
        """(M, d) velocity [m/s] at (M, d) points [m], interpolated (clamped to the domain)."""
        p = as_float_array(points, "points", ndim=2)
        if p.shape[1] != self.dim:
            raise ValueError(f"points: expected shape (M, {self.dim}), got {p.shape}")
        return finite_result(self._core.velocity_at(p), "velocity_at")

    def kinetic_energy(self) -> float:
        """0.5 * integral of |u|^2 over the domain (density 1) [m^(d+2)/s^2]."""
        return finite_result(self._core.kinetic_energy(), "kinetic_energy")

    def max_speed(self) -> float:
        return finite_result(self._core.max_speed(), "max_speed")


class _Record:
    """A run kept by km.grid for km.diff (Fluid._diff_record)."""

    def __init__(self, fluid, record):
        self._fluid, self._record = fluid, record

    def backward(self, grad_after, params):
        want_nu = "viscosity" in params
        grads, g_nu, g_controls = self._record.backward(grad_after, want_nu)
        return grads, ({"viscosity": g_nu} if want_nu else {}), g_controls


def _max_dt(max_dt):
    return float("inf") if max_dt is None else real(max_dt, "max_dt")


def advect(q, velocity, dt, h, scheme="maccormack", rk_order=2, *, periodic=False):
    """Advects the cell-centred scalar ``q`` through the MAC ``velocity = (u, v[, w])`` over dt
    [s] on cells of size h [m], as :class:`Fluid` does (closed domain: back-traces are clamped
    to it; ``periodic=True`` wraps them). Returns the new field."""
    qa = as_float_array(q, "q", ndim=(2, 3))
    d = qa.ndim
    if len(velocity) != d:
        raise ValueError(f"velocity: expected {d} MAC components for a {d}D q, got {len(velocity)}")
    comps = []
    for c, comp in enumerate(velocity):
        a = as_float_array(comp, f"velocity[{c}]", ndim=d)
        want = tuple(n + (1 if i == c else 0) for i, n in enumerate(qa.shape))
        if a.shape != want:
            raise ValueError(f"velocity[{c}]: expected shape {want}, got {a.shape}")
        comps.append(a)
    dt = finite(dt, "dt")
    scheme = getattr(_core.grid.AdvectionScheme, choice(scheme, "scheme", SCHEMES))
    return _core.grid.advect(qa, comps, dt, spacing(h, "h"), scheme, _rk(rk_order), bool(periodic))
