"""Smoothed particle hydrodynamics for liquids: WCSPH and DFSPH in 2D and 3D.

* ``method="wcsph"``: weakly compressible SPH (Becker and Teschner 2007), Tait equation of state
  p = B((rho/rho0)^gamma - 1), B = rho0 c^2 / gamma, symmetric pressure force, symplectic Euler.
* ``method="dfsph"``: divergence-free SPH (Bender and Koschier 2015, 2017): a divergence-free
  and a constant-density solver, so steps far larger than WCSPH's acoustic limit.

Neighbours come from a uniform cell grid built by counting sort into flat CSR arrays; particles
are reordered along a Morton curve every ``reorder_every`` steps for cache locality. Static
solids are boundary samples (``boundary``) with the volume correction of Akinci et al. 2012;
``domain=(lower, upper)`` adds the walls of a closed box (two layers of samples just outside
it, as :func:`box_boundary` places them, with their exact lattice volume) and clamps particles
into it (particles started outside are moved in by the first step).

Kernel: the cubic spline of the course notes (Koschier et al. 2019) with support radius
h = 2 * spacing; particle mass = rho0 * spacing^d.
"""

from __future__ import annotations

import warnings

import numpy as np

from kinema import _core
from kinema._checks import (
    as_float_array, choice, finite_result, integer, positive, positive_int, real, simulation_object,
    spacing as _spacing, time_step)
from kinema._state import assign
from kinema.errors import StabilityError

__all__ = ["Fluid", "neighbor_pairs", "kernel", "block", "box_boundary", "martin_moyce", "METHODS"]

METHODS = ("wcsph", "dfsph")


def _points(points, name):
    a = as_float_array(points, name, ndim=2)
    if a.shape[1] not in (2, 3):
        raise ValueError(f"{name}: expected shape (n, 2) or (n, 3), got {a.shape}")
    return a


def _box(lower, upper, name_lower="lower", name_upper="upper"):
    lo = as_float_array(lower, name_lower, ndim=1)
    hi = as_float_array(upper, name_upper, ndim=1)
    if lo.size not in (2, 3):
        raise ValueError(f"{name_lower}: expected 2 or 3 coordinates, got {lo.size}")
    if hi.shape != lo.shape:
        raise ValueError(f"{name_upper}: expected {lo.size} coordinates like {name_lower}, got {hi.size}")
    if not (hi > lo).all():
        raise ValueError(f"{name_upper}: expected {name_upper} > {name_lower} on every axis, got "
                         f"{name_lower}={lo.tolist()}, {name_upper}={hi.tolist()}")
    return lo, hi


def martin_moyce() -> np.ndarray:
    """Martin and Moyce (1952), Fig. 3: surge-front positions of a collapsing water column of
    width a and height 2a, as an (m, 2) array of (T, Z) with T = t sqrt(2 g / a), Z = z / a
    (as digitised for PySPH's dam-break examples). The validation data of dam-break runs.
    """
    return np.array([(0.832, 1.217), (1.219, 1.474), (1.997, 2.292), (2.547, 2.995),
                     (3.345, 4.134), (4.034, 4.944)])


def neighbor_pairs(points, radius) -> np.ndarray:
    """All pairs i < j with |x_i - x_j| < radius, as an (P, 2) int64 array sorted lexicographically.

    points: (N, d) [m], d = 2 or 3. radius: > 0 [m].
    """
    x = _points(points, "points")
    r = _spacing(radius, "radius")
    return _core.sph.neighbor_pairs(x, r)


def kernel(r, h, d, derivative=0):
    """The cubic spline kernel W(r, h) (support h) in d dimensions, or its radial derivative.

    sigma_2 = 40/(7 pi h^2), sigma_3 = 8/(pi h^3); W = sigma (6(q^3 - q^2) + 1) for q = r/h <= 1/2,
    2 sigma (1 - q)^3 for 1/2 < q <= 1, 0 beyond. derivative: 0 (W), 1 (dW/dr) or 2 (d2W/dr2).
    Returns an array of r's shape (a float for a scalar r).
    """
    scalar = np.ndim(r) == 0
    ra = as_float_array(np.atleast_1d(r), "r")
    if (ra < 0).any():
        raise ValueError("r: expected distances >= 0")
    h = _spacing(h, "h")
    if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d not in (2, 3):
        raise ValueError(f"d: expected 2 or 3, got {d!r}")
    choice(derivative, "derivative", (0, 1, 2))
    out = _core.sph.kernel(ra, h, int(d), int(derivative))
    return float(out[0]) if scalar else out


def block(lower, upper, spacing) -> np.ndarray:
    """A regular lattice filling the box [lower, upper], first point at lower + spacing/2.

    Returns (n, d) positions: every lattice point whose centre lies in the box.
    """
    lo, hi = _box(lower, upper)
    s = _spacing(spacing, "spacing")
    if np.prod(np.floor((hi - lo) / s + 0.5)) > 2**31:
        raise ValueError(f"spacing: {s} gives more than 2^31 particles for this box")
    return _core.sph.block(lo.tolist(), hi.tolist(), s)


def box_boundary(lower, upper, spacing, layers=2) -> np.ndarray:
    """Boundary samples in ``layers`` layers just outside the walls of the box [lower, upper].

    The spacing along each wall is stretched slightly so that the samples fit the box exactly.
    Two layers cover the support (2 * spacing) of a fluid particle at the wall.
    """
    lo, hi = _box(lower, upper)
    s = _spacing(spacing, "spacing")
    layers = positive_int(layers, "layers")
    if np.prod((hi - lo) / s + 2 * layers + 1) > 2**31:
        raise ValueError(f"spacing: {s} gives more than 2^31 boundary samples for this box")
    return _core.sph.box_boundary(lo.tolist(), hi.tolist(), s, layers)


INT32_MAX = 2**31 - 1


@simulation_object
class Fluid:
    """An SPH liquid (2D or 3D) of particles of equal mass rho0 * spacing^d.

    positions: (n, d) initial positions [m]. spacing: particle spacing [m] (support radius
    h = 2 * spacing). method: "wcsph" or "dfsph". rho0: rest density [kg/m^d].
    viscosity: kinematic viscosity [m^2/s] (0 skips the pass). gravity: (d,) [m/s^2]; None
    means no gravity (pass ``(0, -9.81)`` or ``(0, -9.81, 0)`` for water in a tank).
    domain: (lower, upper) of a closed box. boundary: (M, d) static boundary samples of any
    solid. Walls (docs/guide/sph.md, "Walls and energy"): under WCSPH the domain's walls carry
    the pressure of their own density rho_b = sum_k psi_k W_bk + sum_i m W_ib, so the wall
    force is the gradient of the fluid's energy (a column at rest keeps its energy) and the
    pressure beside a wall is hydrostatic; ``boundary`` samples act with Akinci et al. 2012's
    single term (conservative, about twice the hydrostatic pressure beside them). DFSPH's walls
    carry one stiffness per wall sample (``walls``, below): conservative and hydrostatic beside
    them.
    speed_of_sound: WCSPH's c [m/s], default 10 sqrt(2 |g| H) for the initial fluid
    height H. gamma: Tait exponent.
    Further keywords: velocity ((n, d) initial velocities), tol (DFSPH mean density error,
    default 1e-3), divergence_tol (1e-3), max_iter (100), divergence_solve (True),
    reorder_every (least steps between Morton reorderings, 16; 0 keeps the input order),
    neighbor_skin (Verlet skin of the neighbour lists as a fraction of h, 0.2: the cell-grid
    search reruns only when a particle has moved half the skin; 0 searches every step),
    warm_start (DFSPH: share of the last step's stiffnesses each solve starts from, 0.5,
    scaled for a change of dt; it halved the density iterations of a collapsing column, while
    1.0 overshot and diverged: the density solve gives back only what the warm start gave, at
    half the rate), coarse_correction (DFSPH with gravity; None: on where tol > 1e-3, True,
    False: a density solve whose warm start already ends within tol first takes a two-level
    correction, an exact Galerkin solve for one stiffness per layer of height 3 h, which
    rebuilds the hydrostatic pressure a Jacobi iteration rebuilds by ~1% per iteration; without
    it a column at rest at tol 2e-3 sank and bounced; at tol <= 1e-3 the column holds without it
    and on a 3D dam break at tol 1e-4 it cost 0.84x), walls (DFSPH with a domain; None, the default,
    or "shepard": each wall sample carries the Shepard average of its fluid neighbours'
    stiffness, so the wall force has a constraint form and a column filling its tank keeps its
    energy; "mirror", the default before issue 15: each sample mirrors the stiffness of the
    particle it pushes, which is not conservative: a column filling its tank gains energy;
    WCSPH takes None only, its walls carry the pressure of their own density;
    docs/guide/sph.md, "Walls and energy"). ``config`` holds them all (a ``kinema._core.sph.Config``, read-only here).

    State (writable zero-copy views of the solver's memory; they stay valid for the life of
    the Fluid, but Morton reordering permutes rows in place, so row k of ``x`` is the particle
    given as row ``ids[k]`` of ``positions``):

    * x: (n, d) positions [m]; v: (n, d) velocities [m/s]
    * density: (n,) [kg/m^d] at the start of the last step (``density_error()`` refreshes it)
    * pressure: (n,) [Pa] of the last step (DFSPH: p_i = kappa_i rho_i of its constant-density
      and divergence-free solves together, the pressure whose force they applied)
    * ids: (n,) int64 original index of each row; time [s]

    :meth:`state` and :meth:`set_state` hold these and what a step reads from the earlier ones
    (DFSPH's warm-start stiffnesses, the neighbour lists, the last dt), so a run resumed from a
    state is bitwise the run that was not stopped.
    """

    #: the differentiable parameters (km.diff)
    parameters = ("viscosity",)

    def __init__(self, positions, spacing, *, method="dfsph", rho0=1000.0, viscosity=0.0,
                 gravity=None, domain=None, boundary=None, speed_of_sound=None, gamma=7.0,
                 velocity=None, tol=1e-3, divergence_tol=1e-3, max_iter=100,
                 divergence_solve=True, reorder_every=16, neighbor_skin=0.2, warm_start=0.5,
                 coarse_correction=None, walls=None):
        x = _points(positions, "positions")
        n, d = x.shape
        self.dim = d
        if not isinstance(method, str):
            raise ValueError(f"method: expected one of {list(METHODS)}, got {method!r}")
        self.spacing = _spacing(spacing, "spacing")
        config = _core.sph.Config()
        config.method = _core.sph.parse_method(method)
        config.rho0 = real(rho0, "rho0")
        config.viscosity = real(viscosity, "viscosity")
        if gravity is not None:
            g = as_float_array(gravity, "gravity", ndim=1)
            if g.size != d:
                raise ValueError(f"gravity: expected {d} components for {d}D positions, got {g.size}")
            config.gravity = np.r_[g, np.zeros(3 - d)].tolist()
        if velocity is None:
            v = np.zeros_like(x)
        else:
            v = as_float_array(velocity, "velocity")
            if v.shape != x.shape:
                raise ValueError(f"velocity: expected shape {x.shape} like positions, got {v.shape}")
        if speed_of_sound is not None:
            config.speed_of_sound = real(speed_of_sound, "speed_of_sound")
            if config.speed_of_sound == 0:  # 0 would mean "derive it"
                raise ValueError("speed_of_sound: expected a finite number > 0, got 0.0")
        config.gamma = real(gamma, "gamma")
        config.tol = real(tol, "tol")
        config.divergence_tol = real(divergence_tol, "divergence_tol")
        config.max_iter = integer(max_iter, "max_iter", high=INT32_MAX)
        config.divergence_solve = bool(divergence_solve)
        config.reorder_every = integer(reorder_every, "reorder_every", high=INT32_MAX)
        config.neighbor_skin = real(neighbor_skin, "neighbor_skin")
        config.warm_start = real(warm_start, "warm_start")
        config.coarse_correction = -1 if coarse_correction is None else int(bool(coarse_correction))
        if walls is not None and (not isinstance(walls, str) or walls not in ("mirror", "shepard")):
            raise ValueError(f"walls: expected None, 'mirror' or 'shepard', got {walls!r}")
        if walls is not None and method == "wcsph":
            raise ValueError(f"walls: {walls!r} is DFSPH's (WCSPH's walls carry the pressure of their own density; "
                             "leave walls=None)")
        config.shepard_walls = walls != "mirror"

        lower = upper = None
        if domain is not None:
            try:
                lower, upper = domain
            except (TypeError, ValueError):
                raise ValueError("domain: expected (lower, upper), two points of d coordinates") from None
            lower = as_float_array(lower, "domain lower", ndim=1)
            upper = as_float_array(upper, "domain upper", ndim=1)
            if lower.size != d or upper.size != d:
                raise ValueError(f"domain: expected {d} coordinates per corner for {d}D positions, "
                                 f"got {lower.size} and {upper.size}")
        xb = None
        if boundary is not None:
            xb = as_float_array(boundary, "boundary", ndim=2)
            if xb.shape[1] != d:
                raise ValueError(f"boundary: expected shape (M, {d}) for {d}D positions, got {xb.shape}")
        self._core = _core.sph.Fluid(x, v, self.spacing, config, xb,
                                     None if lower is None else lower.tolist(),
                                     None if upper is None else upper.tolist())
        self.domain = None if lower is None else (lower, upper)
        self.last_stats = None

    # ------------------------------------------------------------------ configuration
    @property
    def config(self):
        """The parameters (a copy: changing it changes nothing)."""
        return self._core.config

    @property
    def method(self) -> str:
        """"wcsph" or "dfsph"."""
        return self._core.config.method.name.lower()

    @property
    def rho0(self) -> float:
        """Rest density [kg/m^d]."""
        return self._core.config.rho0

    @property
    def viscosity(self) -> float:
        """Kinematic viscosity [m^2/s]."""
        return self._core.config.viscosity

    @property
    def gravity(self) -> np.ndarray:
        """(d,) [m/s^2]."""
        return np.array(self._core.config.gravity[:self.dim])

    # ------------------------------------------------------------------ state
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
    def density(self) -> np.ndarray:
        """(n,) densities [kg/m^d] at the start of the last step (writable view; recomputed
        by every step)."""
        return self._core.density

    @density.setter
    def density(self, value):
        assign(self.density, value, "density")

    @property
    def pressure(self) -> np.ndarray:
        """(n,) pressures [Pa] of the last step (writable view; recomputed by every step)."""
        return self._core.pressure

    @pressure.setter
    def pressure(self, value):
        assign(self.pressure, value, "pressure")

    @property
    def ids(self) -> np.ndarray:
        """(n,) int64: row k holds the particle given as row ids[k] of the initial positions."""
        return self._core.ids

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._core.time

    @property
    def steps(self) -> int:
        """Steps taken."""
        return self._core.steps

    @property
    def n(self) -> int:
        return self.x.shape[0]

    @property
    def mass(self) -> float:
        """Particle mass rho0 * spacing^d [kg]."""
        return self._core.mass

    @property
    def support_radius(self) -> float:
        """Kernel support h = 2 * spacing [m]."""
        return self._core.support_radius

    @property
    def speed_of_sound(self) -> float:
        """WCSPH's c (DFSPH: the reference speed of its blow-up check) [m/s]."""
        return self._core.speed_of_sound

    @property
    def boundary_count(self) -> int:
        """Number of boundary samples (domain walls and ``boundary``)."""
        return self._core.boundary_count

    @property
    def boundary_psi(self) -> np.ndarray:
        """(M,) rho0 V_b of each boundary sample [kg] (Akinci et al. 2012, eq. 4): the
        ``boundary`` samples first, then the domain's walls."""
        return self._core.boundary_psi

    _STATE_SCALARS = ("time", "steps", "last_dt", "reorder_step", "neighbor_skin")

    def state(self) -> dict:
        """Copies of everything that evolves: x, v, density, pressure, ids, time, steps; the
        last dt and the step of the last reordering; DFSPH's stiffnesses kappa_density and
        kappa_divergence ((n,) p_i / rho_i^2 of each solve, the next solves' warm start); and
        the neighbour lists as the positions neighbor_x ((n, d), or (0, d) before the first
        step) and skin neighbor_skin they were built with."""
        return self._core.state()

    def set_state(self, state: dict) -> None:
        """Restores a :meth:`state` of this fluid (or of one built alike) exactly: the resumed
        run is bitwise the run that was not stopped. A refused dict changes nothing."""
        if not isinstance(state, dict):
            raise ValueError(f"state: expected a dict from state(), got {type(state).__name__}")
        keys = ("x", "v", "density", "pressure", "ids", "neighbor_x", *self._STATE_SCALARS)
        if self.method == "dfsph":
            keys += ("kappa_density", "kappa_divergence")
        missing = [k for k in keys if k not in state]
        if missing:
            raise ValueError(f"state: missing {missing[0]!r}")
        if np.asarray(state["ids"]).dtype.kind not in "iu":
            raise ValueError(f"state['ids']: expected integers, got {np.asarray(state['ids']).dtype}")
        scalars = {k: (integer if k in ("steps", "reorder_step") else real)(
            np.asarray(state[k])[()], f"state[{k!r}]") for k in self._STATE_SCALARS}
        self._core.set_state(state, **scalars)

    # ------------------------------------------------------------------ stepping
    def step(self, dt, check=True):
        """Advances by dt [s]; returns the step's ``kinema._core.sph.StepStats`` (time, dt,
        seconds, iterations, divergence_iterations, density_error, divergence_error,
        density_converged and divergence_converged (DFSPH: False when the solve stopped at
        max_iter above its tolerance), max_speed, neighbor_count, neighbor_rebuild, and the
        step's wall time split into search_seconds, kernel_seconds and solve_seconds: the
        neighbour search, the kernel pass and the pressure solves).

        check: raise km.StabilityError (naming dt) for a step beyond :meth:`stability_limit`,
        the limit of the scheme's explicit parts; ``check=False`` takes it anyway. Raises
        km.DivergenceError when a value turns non-finite or speeds run away (dt too large: see
        :meth:`stable_dt`); the state is then as before the step.
        """
        dt = time_step(dt)
        if check:
            limit = self.stability_limit()
            if dt > limit:
                raise StabilityError(f"dt: {dt:.6g} s is beyond {self.method.upper()}'s stability limit "
                                     f"{limit:.6g} s (stability_limit(); advance() and stable_dt() stay "
                                     "below it; pass check=False to take the step anyway)")
        return self._core.step(dt)

    def stability_limit(self) -> float:
        """The largest step the explicit parts of the scheme tolerate [s], from the current
        velocities: WCSPH's acoustic Courant limit spacing / (c + v_max) (a dam break of 20^2
        or 10^3 particles runs at 1.5 times it and diverges at 2-3 times it:
        tests/test_sph.py::test_wcsph_stability_limit_is_where_it_diverges), and for either method with viscosity
        forward Euler's bound 2 / lambda_max on the viscosity term, lambda_max = 19.3 nu /
        spacing^2 in 2D, 21.4 in 3D (the measured spectrum of settled fluid, see
        :meth:`stable_dt`). DFSPH's pressure is implicit: without viscosity it has no limit
        here (inf; :meth:`stable_dt`'s CFL rule keeps it accurate)."""
        limit = np.inf
        if self.method == "wcsph":
            vmax = float(np.sqrt((np.asarray(self.v) ** 2).sum(axis=1).max())) if len(self.v) else 0.0
            limit = self.spacing / (self.speed_of_sound + vmax)
        if self.viscosity > 0:
            lam = 19.3 if self.x.shape[1] == 2 else 21.4
            limit = min(limit, 2.0 / lam * self.spacing ** 2 / self.viscosity)
        return limit

    def advance(self, duration, cfl=0.4) -> int:
        """Advances by ``duration`` [s] in steps of :meth:`stable_dt` (cfl), the last one
        landing on the end; returns the step count (the last step's stats in ``last_stats``).

        DFSPH: when a pressure solve stops at ``max_iter`` above its tolerance (the step's
        ``density_converged`` / ``divergence_converged`` are False), warns (RuntimeWarning) once
        per call with the count of such steps and their largest density error."""
        duration = real(duration, "duration")
        cfl = real(cfl, "cfl")
        if duration == 0:
            return 0
        steps, self.last_stats, unconverged, worst = self._core.advance(duration, cfl)
        if unconverged:
            warnings.warn(f"sph: in {unconverged} of {steps} steps a DFSPH pressure solve stopped at max_iter="
                          f"{self.config.max_iter} above its tolerance (largest density error {worst:.3g}, tol "
                          f"{self.config.tol:.3g}); raise max_iter or lower cfl", RuntimeWarning, stacklevel=2)
        return steps

    def stable_dt(self, cfl=0.4) -> float:
        """The CFL step cfl * spacing / (c + v_max) (WCSPH) or cfl * spacing / v_max (DFSPH),
        also bounded by the viscous limit 0.05 spacing^2 / nu, sqrt(0.1 cfl spacing / |g|) and
        5 ms."""
        return self._core.stable_dt(real(cfl, "cfl"))

    def kinetic_energy(self) -> float:
        """0.5 * m * sum |v|^2 [J] (2D: per unit depth)."""
        v = self.v
        return finite_result(0.5 * self.mass * float(np.einsum("ij,ij->", v, v)), "kinetic_energy")

    def neighbor_pairs(self):
        """The neighbour pairs the next step will use, brought up to date as a step does.

        Returns (fluid, boundary): (P, 2) int64 row pairs i < j of ``x`` closer than the support
        radius, and (Q, 2) pairs (row i, boundary sample b) closer than it.
        """
        return self._core.neighbor_pairs_in_use()

    def density_error(self) -> float:
        """Mean over particles of max(rho/rho0 - 1, 0) at the current positions (refreshes
        ``density``, and for WCSPH ``pressure``)."""
        return finite_result(self._core.density_error(), "density_error")

    # ------------------------------------------------------------------ km.diff protocol
    # Gradients of WCSPH steps with respect to x, v, the per-step particle forces (controls) and
    # viscosity (docs/guide/diff.md). The neighbour set of each step is the forward's (not
    # differentiated); Tait's clamp of negative pressures and the domain clamp are differentiated
    # on the branch taken. A control row is the force [N] on a particle by its id (row i acts on
    # the particle given as row i of ``positions``), so it follows the particle through Morton
    # reorderings; gradients of x and v are by row of the state they belong to, as ``x`` is.
    _diff_state_names = ("x", "v")

    def _diff_check(self, wrt, step_options):
        for option in step_options:
            raise ValueError(f"{option}: km.sph.Fluid.step takes no option besides dt")
        if self.method != "wcsph":
            raise ValueError(f"method: gradients need method='wcsph', this fluid is {self.method!r} (DFSPH's "
                             "pressure solves are projected Jacobi iterations stopped at a tolerance, with clamped "
                             "increments and a warm start: not differentiable as run, see docs/guide/diff.md)")
        allowed = self._diff_state_names + self.parameters + ("controls",)
        for name in wrt:
            if name not in allowed:
                raise ValueError(f"wrt: {name!r} is not differentiable in km.sph.Fluid (expected one of {allowed})")

    def _diff_control_shape(self):
        return (self.n, self.dim)

    def _diff_get(self, name):
        if name in self._diff_state_names:
            return getattr(self, name).copy()
        if name == "viscosity":
            return self.viscosity
        raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.sph.Fluid")

    def _diff_set(self, name, value):
        if name in self._diff_state_names:
            setattr(self, name, value)
        elif name == "viscosity":
            self._core.set_viscosity(real(value, "viscosity"))
        else:
            raise ValueError(f"name: {name!r} is neither a state array nor a parameter of km.sph.Fluid")

    def _diff_step(self, dt, control, step_options):
        self._diff_check((), step_options)
        return self._core.step(time_step(dt), control)

    def _diff_step_adjoint(self, dt, before, after, control, grad_after, step_options):
        self._diff_check((), step_options)
        gx = as_float_array(grad_after["x"], "grads['x']")
        gv = as_float_array(grad_after["v"], "grads['v']")
        gx_before, gv_before, g_nu, g_control = self._core.step_adjoint(
            time_step(dt), before, after, gx, gv, control is not None)
        return {"x": gx_before, "v": gv_before}, {"viscosity": g_nu}, g_control


# ---------------------------------------------------------------------- obstacle sampling
# Boundary samples of solids other than boxes, for Fluid(boundary=...). Like box_boundary they
# fill `layers` layers on the solid's side of its surface, layer k at depth (k + 1/2) spacing,
# so that two layers cover the support (2 * spacing) of a fluid particle touching the surface;
# Akinci et al. 2012's volume correction (applied by Fluid) evens out what irregularity is left.
__all__ += ["sphere_boundary", "mesh_boundary"]


def _sphere_points(n, dim):
    """n nearly uniform unit vectors: equal angles on the circle, the Fibonacci lattice on the sphere."""
    k = np.arange(n) + 0.5
    if dim == 2:
        t = 2 * np.pi * k / n
        return np.stack([np.cos(t), np.sin(t)], 1)
    z = 1 - 2 * k / n
    r = np.sqrt(np.maximum(0.0, 1 - z * z))
    phi = np.pi * (3 - np.sqrt(5)) * np.arange(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def sphere_boundary(center, radius, spacing, layers=2, *, fluid="outside") -> np.ndarray:
    """Boundary samples of a sphere (3D) or circle (2D) of ``radius`` [m] about ``center``.

    fluid: "outside" (a solid ball, the obstacle) puts the layers inside the sphere at radii
    radius - (k + 1/2) spacing; "inside" (a spherical container) puts them outside, at radius +
    (k + 1/2) spacing. Each layer holds round(area / spacing^(d-1)) samples spread evenly (equal
    angles on a circle, the Fibonacci lattice on a sphere), so neighbouring samples are about
    ``spacing`` apart; a layer whose radius would be below spacing / 2 becomes one centre sample.
    Returns (M, d) positions [m].
    """
    c = as_float_array(center, "center", ndim=1)
    if c.size not in (2, 3):
        raise ValueError(f"center: expected 2 or 3 coordinates, got {c.size}")
    r = positive(radius, "radius")
    s = positive(spacing, "spacing")
    layers = positive_int(layers, "layers")
    choice(fluid, "fluid", ("outside", "inside"))
    dim = c.size
    sign = -1.0 if fluid == "outside" else 1.0
    parts = []
    for k in range(layers):
        rk = r + sign * (k + 0.5) * s
        if rk < 0.5 * s:
            parts.append(c[None, :].copy())
            break
        area = 2 * np.pi * rk if dim == 2 else 4 * np.pi * rk * rk
        n = max(1, int(round(area / s ** (dim - 1))))
        if n > 2**31:
            raise ValueError(f"spacing: {s} gives more than 2^31 samples on a sphere of radius {r}")
        parts.append(c + rk * _sphere_points(n, dim))
    return np.ascontiguousarray(np.concatenate(parts))


def _segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _triangle_distance(p, a, b, c):
    """Distance from points p to triangles (a, b, c), row by row."""
    n = np.cross(b - a, c - a)
    nn = np.linalg.norm(n, axis=1)
    unit = n / np.maximum(nn, 1e-300)[:, None]
    # inside the prism over the triangle when p lies left of all three edges (seen along n)
    inside = np.ones(len(p), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, p - u), n) >= 0
    plane = np.abs(np.einsum("ij,ij->i", p - a, unit))
    edge = np.minimum(np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c)),
                      _segment_distance(p, c, a))
    return np.where(inside & (nn > 0), plane, edge)


def _winding_number(points, v, f):
    """Generalised winding number of closed oriented triangles (3D, Van Oosterom and Strackee's
    solid angle) or segments (2D, signed angles) about each point: 1 inside, 0 outside."""
    out = np.empty(len(points))
    chunk = max(1, (1 << 20) // len(f))  # points per pass: about a million point-face pairs
    for s0 in range(0, len(points), chunk):
        p = points[s0:s0 + chunk, None, :]
        if v.shape[1] == 2:
            a, b = v[f[:, 0]][None] - p, v[f[:, 1]][None] - p
            ang = np.arctan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], np.einsum("...i,...i", a, b))
            out[s0:s0 + chunk] = ang.sum(1) / (2 * np.pi)
        else:
            a, b, c = v[f[:, 0]][None] - p, v[f[:, 1]][None] - p, v[f[:, 2]][None] - p
            la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
            num = np.einsum("...i,...i", a, np.cross(b, c))
            den = (la * lb * lc + np.einsum("...i,...i", a, b) * lc + np.einsum("...i,...i", b, c) * la
                   + np.einsum("...i,...i", c, a) * lb)
            out[s0:s0 + chunk] = 2 * np.arctan2(num, den).sum(1) / (4 * np.pi)
    return out


def mesh_boundary(vertices, faces, spacing, layers=2, *, fluid="outside") -> np.ndarray:
    """Boundary samples of a solid bounded by a closed, outward-oriented triangle mesh (3D:
    ``faces`` (F, 3)) or polygon (2D: ``faces`` (F, 2) edges, interior on their left), such as
    :func:`kinema.mesh.surface` returns.

    The samples are the points of the lattice of ``spacing`` centred on the mesh's bounding box
    (a box of whole cells has them at the cell centres, as :func:`block`) whose distance to the surface is below ``layers * spacing`` on the solid's side:
    inside the surface for ``fluid="outside"`` (an obstacle), outside it for ``fluid="inside"``
    (a container). Inside and outside are told by the generalised winding number (Jacobson et
    al. 2013), so small gaps in the surface do not flip them. Returns (M, d) positions [m].
    """
    from scipy.spatial import cKDTree

    v = _points(vertices, "vertices")
    dim = v.shape[1]
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != dim or f.dtype.kind not in "iu":
        raise ValueError(f"faces: expected an integer array of shape (F, {dim}) for {dim}D vertices, "
                         f"got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    if len(f) == 0 or f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"faces: expected at least one face with vertex indices in [0, {len(v)})")
    s = positive(spacing, "spacing")
    layers = positive_int(layers, "layers")
    choice(fluid, "fluid", ("outside", "inside"))
    band = layers * s
    pad = band if fluid == "inside" else 0.0
    lo, hi = v.min(0) - pad, v.max(0) + pad
    counts = np.maximum(1, np.round((hi - lo) / s)).astype(np.int64)  # one point per cell of the box
    if np.prod(counts.astype(float)) > 2**31:
        raise ValueError(f"spacing: {s} gives more than 2^31 lattice points over the mesh")
    start = lo + 0.5 * ((hi - lo) - (counts - 1) * s)  # the lattice centred on the box
    axes = [start[a] + s * np.arange(counts[a]) for a in range(dim)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim)
    # Distances only for the lattice points near some face: each face's candidates are the points
    # within band + its circumradius about its centroid.
    corners = v[f]
    centroid = corners.mean(1)
    reach = band + np.linalg.norm(corners - centroid[:, None], axis=2).max(1)
    tree = cKDTree(grid)
    near = tree.query_ball_point(centroid, reach)
    face_of = np.repeat(np.arange(len(f)), [len(n) for n in near])
    point_of = np.fromiter((i for n in near for i in n), np.int64, count=len(face_of))
    dist = np.full(len(grid), np.inf)
    for c0 in range(0, len(face_of), 1 << 18):
        pf, pp = face_of[c0:c0 + (1 << 18)], point_of[c0:c0 + (1 << 18)]
        if dim == 2:
            d = _segment_distance(grid[pp], v[f[pf, 0]], v[f[pf, 1]])
        else:
            d = _triangle_distance(grid[pp], v[f[pf, 0]], v[f[pf, 1]], v[f[pf, 2]])
        np.minimum.at(dist, pp, d)
    cand = np.flatnonzero(dist < band)
    inside = _winding_number(grid[cand], v, f) > 0.5
    keep = cand[inside] if fluid == "outside" else cand[~inside]
    return np.ascontiguousarray(grid[keep])
