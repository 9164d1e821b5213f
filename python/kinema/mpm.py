"""The material point method: MLS-MPM (Hu et al. 2018) with APIC transfers (Jiang et al. 2015),
quadratic B-spline weights, in 2D and 3D, for elastic solids, snow, sand and water in one
simulation.

    sim = km.mpm.Simulation((64, 64), h=1/64)
    rows = sim.add_particles(km.mpm.block((0.3, 0.5), (0.5, 0.7), 1/128), "elastic",
                             density=1000, youngs_modulus=1e5, poisson_ratio=0.3)
    sim.advance(1.0)

Materials (``material=``):

* ``"elastic"``: fixed-corotated hyperelasticity (Stomakhin et al. 2012);
* ``"neohookean"``: stable neo-Hookean (Smith, de Goes and Kim 2018), robust to inversion;
* ``"snow"``: fixed-corotated with the plasticity and hardening of Stomakhin et al. 2013
  (critical compression 2.5e-2, stretch 7.5e-3, hardening 10);
* ``"sand"``: Drucker-Prager elastoplasticity with the log-strain return mapping of Klar et al.
  2016 (``friction_angle`` in degrees, optional ``cohesion`` in Pa);
* ``"water"``: weakly compressible, Tait pressure p = K/7 (J^-7 - 1) with bulk modulus
  K = ``youngs_modulus``; F keeps only the volume ratio J.

Domain walls: ``boundary`` in {"sticky", "slip", "separate"} on the nodes at and beyond the walls
of [origin, origin + shape h]; particles are kept inside the domain. Static colliders (box,
sphere) may have Coulomb friction.

The grid is sparse (blocks of 4^3 or 8^2 nodes exist only where particles are) and the
particle-to-grid transfer is deterministic for any thread count. State arrays are writable
views of the solver's memory in the order particles were added; adding particles reallocates
them, so take views again after :meth:`Simulation.add_particles` (an older view stays valid
memory but is detached). While no view is alive the solver may store the rows sorted into grid
blocks (faster transfers), and each step keeps the last one's binning of the particles into
blocks, re-binning only those that left their block; taking a view puts the rows back first and
makes the next step sort all particles. Results do not depend on either.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from kinema import _core
from kinema._checks import (
    as_float_array, choice, finite, finite_result, grid_shape, integer, non_negative, positive,
    simulation_object, user_stacklevel)

__all__ = ["Simulation", "Config", "StepStats", "block", "sphere", "MATERIALS", "BOUNDARIES", "MU_I_GLASS_BEADS"]

Config = _core.mpm.Config
StepStats = _core.mpm.StepStats

MATERIALS = ("elastic", "neohookean", "snow", "sand", "water")
BOUNDARIES = ("sticky", "slip", "separate")

# Young's modulus [Pa] and Poisson ratio of each material when not given: a soft jelly, snow
# and sand of Stomakhin et al. 2013 and Klar et al. 2016, and water's bulk modulus chosen for a
# sound speed of 50 m/s at 1000 kg/m^3 (Mach < 0.1 for flows below 5 m/s, about 1% compression).
# The mu(I) parameters of Jop, Forterre and Pouliquen 2006 (Nature 441, 727) for their glass
# beads: the defaults of add_particles(..., friction_law="mu_i").
MU_I_GLASS_BEADS = {"mu_s": math.tan(math.radians(20.9)), "mu_2": math.tan(math.radians(32.76)), "I0": 0.279,
                    "grain_diameter": 0.53e-3, "grain_density": 2450.0}

DEFAULTS = {
    "elastic": (1e5, 0.3),
    "neohookean": (1e5, 0.3),
    "snow": (1.4e5, 0.2),
    "sand": (3.537e5, 0.3),
    "water": (2.5e6, 0.0),
}


def block(lower, upper, spacing) -> np.ndarray:
    """A regular lattice filling the box [lower, upper], first point at lower + spacing/2,
    row-major: (n, d) positions."""
    lo = as_float_array(lower, "lower", ndim=1)
    hi = as_float_array(upper, "upper", ndim=1)
    s = positive(spacing, "spacing")
    if lo.size not in (2, 3) or hi.shape != lo.shape:
        raise ValueError(f"lower, upper: expected 2 or 3 coordinates each, got {lo.size} and {hi.size}")
    counts = np.floor((hi - lo) / s + 1e-9).astype(int)
    if (counts < 1).any():
        raise ValueError(f"spacing: {s} does not fit in the box {lo.tolist()}..{hi.tolist()}")
    axes = [lo[a] + s * (np.arange(counts[a]) + 0.5) for a in range(lo.size)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, lo.size)


def sphere(center, radius, spacing) -> np.ndarray:
    """The points of a regular lattice of ``spacing`` inside the ball (disk in 2D) of
    ``radius`` about ``center``: (n, d) positions."""
    c = as_float_array(center, "center", ndim=1)
    r = positive(radius, "radius")
    x = block(c - r, c + r, spacing)
    return x[np.linalg.norm(x - c, axis=1) <= r]


def _lattice_volume(x):
    """spacing^d of a lattice-like point set: the median nearest-neighbour distance."""
    from scipy.spatial import cKDTree

    if len(x) < 2:
        raise ValueError("volume: cannot estimate a spacing from fewer than 2 particles; pass volume=")
    dist, _ = cKDTree(x).query(x, k=2)
    spacing = float(np.median(dist[:, 1]))
    if spacing <= 0:
        raise ValueError("positions: coincident particles; pass volume= explicitly")
    return spacing ** x.shape[1]


@simulation_object
class Simulation:
    """An MPM simulation on a background grid of ``shape`` cells of spacing ``h`` spanning
    [origin, origin + shape h] (origin 0 by default).

    Attributes (writable views over all particles, rows in the order they were added):
    ``x`` (n, d) [m], ``v`` (n, d) [m/s], ``F`` (n, d, d) elastic deformation gradient,
    ``C`` (n, d, d) APIC affine matrix [1/s], ``mass`` (n,) [kg], ``volume`` (n,) rest volumes
    [m^d], ``material`` (n,) int64 index into :attr:`materials`, ``Jp`` (n,) plastic volume ratio
    (snow, sand; 1 otherwise), ``time`` [s].

    ``gravity`` [m/s^2]: None (the default) means no gravity; pass (0, -9.81[, 0]) for Earth's.
    ``friction`` is the Coulomb coefficient of the
    walls (slip and separate; an addition to the API contract, whose walls are frictionless). ``max_cells_per_step``: a step in which a particle
    crosses more cells than this raises :class:`kinema.DivergenceError`. ``max_dt`` caps
    :meth:`stable_dt`. ``adapt_threads``: a step of up to 65,536 particles may run on one thread
    when, timed every 256 steps, one thread is clearly faster than the team (two contended
    cores; results are bitwise the same; :attr:`StepStats.threads` says which). These four are
    the fields of :attr:`config` (a :class:`Config`).

    Gradients (km.diff): ``parameters`` are ``("youngs_modulus", "poisson_ratio")``, one value per
    particle (views ``youngs_modulus`` and ``poisson_ratio`` (n,), initialised from the
    material; the step derives each particle's Lame parameters from them); the differentiable
    state is ``x``, ``v``, ``F``, ``C``; a control is an (n, d) force [N] per particle added to
    the P2G momentum as dt f, where gravity enters. Elastic, neo-Hookean and water particles only
    (``material`` is named in the ValueError otherwise). Where the step switches branch (wall and
    collider conditions, Coulomb sticking, the clamp of x to the domain, a particle's B-spline
    base node) the gradient is that of the branch taken.
    """

    def __init__(self, shape, h, *, gravity=None, boundary="slip", origin=None, friction=0.0,
                 max_cells_per_step=2.0, max_dt=1e-2, adapt_threads=True):
        shape = grid_shape(shape, "shape")
        d = len(shape)
        h = positive(h, "h")
        with np.errstate(all="ignore"):
            hh = np.float64(h)
            resolved = np.isfinite(4 / hh**2) and 0 < hh**d < np.inf and np.isfinite(hh * max(shape))
        if not resolved:
            raise ValueError(f"h: {h:g} m is outside what float64 resolves for the transfers (1/h^2, "
                             f"h^{d} and the domain shape * h must be finite and nonzero); choose other units")
        gravity = np.zeros(d) if gravity is None else as_float_array(gravity, "gravity", ndim=1)
        if gravity.size != d:
            raise ValueError(f"gravity: expected {d} components, got {gravity.size}")
        origin = np.zeros(d) if origin is None else as_float_array(origin, "origin", ndim=1)
        if origin.size != d:
            raise ValueError(f"origin: expected {d} coordinates, got {origin.size}")
        choice(boundary, "boundary", BOUNDARIES)
        config = Config()
        config.gravity = gravity.tolist() + [0.0] * (3 - d)
        config.max_cells_per_step = positive(max_cells_per_step, "max_cells_per_step")
        config.max_dt = positive(max_dt, "max_dt")
        if not isinstance(adapt_threads, (bool, np.bool_)):
            raise ValueError(f"adapt_threads: expected True or False, got {adapt_threads!r}")
        config.adapt_threads = bool(adapt_threads)
        self._sim = _core.mpm.Simulation(list(shape), h, config, _core.mpm.Boundary.__members__[boundary],
                                         origin.tolist(), non_negative(friction, "friction"))
        self.shape = shape
        self.h = h
        self.dim = d
        self.origin = origin
        self.gravity = gravity
        self.boundary = boundary
        self._warned_cfl = 0.0  # the CFL number step() last warned of (0: within the limit since)

    # ---------------------------------------------------------------- building
    def add_particles(self, positions, material, *, density, youngs_modulus=None, poisson_ratio=None,
                      velocity=None, volume=None, friction_angle=None, cohesion=0.0, friction_law="constant",
                      mu_s=None, mu_2=None, I0=None, grain_diameter=None, grain_density=None) -> slice:
        """Adds particles of one material; returns the slice of their rows.

        ``density`` [kg/m^d] and ``volume`` (scalar or (n,), default the lattice spacing^d
        estimated from ``positions``) give each particle's mass. ``youngs_modulus`` [Pa]
        (water: the bulk modulus) and ``poisson_ratio`` default to the material's entry in
        :data:`DEFAULTS`.

        Sand has two friction laws. ``friction_law="constant"`` (the default): a Drucker-Prager
        cone of ``friction_angle`` [deg] (required; Klar et al. 2016), rate independent.
        ``friction_law="mu_i"``: the mu(I) rheology of Jop, Forterre and Pouliquen 2006, the
        friction coefficient |tau| / p = mu_s + (mu_2 - mu_s) / (I0 / I + 1) growing with the
        inertial number I = gamma_dot d / sqrt(p / rho_s) (``grain_diameter`` d [m],
        ``grain_density`` rho_s [kg/m^d] of the grains, not the bulk ``density``); the parameters
        default to Jop et al.'s glass beads (:data:`MU_I_GLASS_BEADS`: mu_s = tan 20.9 deg,
        mu_2 = tan 32.76 deg, I0 = 0.279, d = 0.53 mm, rho_s = 2450 kg/m^3); ``friction_angle``
        is then not used (give ``mu_s``). ``cohesion`` [Pa] moves either cone's apex to the
        tensile pressure cohesion / tan(phi) (cohesion / mu_s).
        """
        choice(material, "material", MATERIALS)
        x = as_float_array(positions, "positions", ndim=2)
        if x.shape[1] != self.dim:
            raise ValueError(f"positions: expected shape (n, {self.dim}), got {x.shape}")
        n = x.shape[0]
        if n == 0:
            raise ValueError("positions: expected at least one particle")
        v = np.zeros_like(x) if velocity is None else as_float_array(velocity, "velocity")
        if v.ndim == 1 and v.size == self.dim:
            v = np.ascontiguousarray(np.broadcast_to(v, x.shape))
        if v.shape != x.shape:
            raise ValueError(f"velocity: expected shape ({self.dim},) or {x.shape}, got {v.shape}")
        if volume is None:
            volume = _lattice_volume(x)
        if np.ndim(volume) == 0:
            volume = np.full(n, positive(volume, "volume"))
        vol = as_float_array(volume, "volume")
        if vol.shape != (n,):
            raise ValueError(f"volume: expected a scalar or shape ({n},), got {vol.shape}")
        e_default, nu_default = DEFAULTS[material]
        e = e_default if youngs_modulus is None else positive(youngs_modulus, "youngs_modulus")
        nu = nu_default if poisson_ratio is None else finite(poisson_ratio, "poisson_ratio")
        choice(friction_law, "friction_law", ("constant", "mu_i"))
        mu_i = dict(MU_I_GLASS_BEADS)
        if friction_law == "mu_i":
            if material != "sand":
                raise ValueError(f"friction_law: 'mu_i' is a law of sand, not of {material!r}")
            if friction_angle is not None:
                raise ValueError("friction_angle: not used by friction_law='mu_i' (give mu_s, the static "
                                 "friction coefficient)")
            for key, value in (("mu_s", mu_s), ("mu_2", mu_2), ("I0", I0), ("grain_diameter", grain_diameter),
                               ("grain_density", grain_density)):
                if value is not None:
                    mu_i[key] = positive(value, key)
            friction_angle = math.degrees(math.atan(mu_i["mu_s"]))
        elif any(v is not None for v in (mu_s, mu_2, I0, grain_diameter, grain_density)):
            raise ValueError("friction_law: mu_s, mu_2, I0, grain_diameter and grain_density belong to "
                             "friction_law='mu_i'")
        if material == "sand":
            if friction_angle is None:
                raise ValueError("friction_angle: sand needs a friction angle in degrees (e.g. 30)")
            phi = positive(friction_angle, "friction_angle")
        else:
            phi = 0.0 if friction_angle is None else finite(friction_angle, "friction_angle")
        start, stop = self._sim.add_particles(x, _core.mpm.MaterialKind.__members__[material], positive(density, "density"), e, nu, v, vol, phi,
                                              non_negative(cohesion, "cohesion"),
                                              friction_law, **(mu_i if friction_law == "mu_i" else {}))
        return slice(start, stop)

    def add_collider(self, region, *, boundary="slip", friction=0.0):
        """A static collider: ``region`` is ``{"shape": "box", "lower": ..., "upper": ...}`` or
        ``{"shape": "sphere", "center": ..., "radius": ...}``; ``boundary`` as the walls',
        ``friction`` the Coulomb coefficient of slip and separate contact."""
        if not isinstance(region, dict) or "shape" not in region:
            raise ValueError(f"region: expected a dict with a 'shape' of 'box' or 'sphere', got {region!r}")
        choice(boundary, "boundary", BOUNDARIES)
        shape = region["shape"]
        choice(shape, "region['shape']", ("box", "sphere"))

        def coords(key):
            if key not in region:
                raise ValueError(f"region: a {shape} needs '{key}'")
            return as_float_array(region[key], f"region['{key}']", ndim=1).tolist()

        if shape == "box":
            lower, upper, center, radius = coords("lower"), coords("upper"), [], 0.0
        else:
            lower, upper, center = [], [], coords("center")
            radius = positive(region.get("radius"), "region['radius']")
        self._sim.add_collider(shape, lower, upper, center, radius, _core.mpm.Boundary.__members__[boundary],
                               non_negative(friction, "friction"))

    # ---------------------------------------------------------------- stepping
    def step(self, dt) -> StepStats:
        """One MLS-MPM step of ``dt`` [s]; returns its :class:`StepStats` (time, dt, seconds,
        per-stage seconds, max_speed, active_blocks, rebinned: the particles binned anew).
        A ``dt`` above :meth:`cfl_dt` of the state the step starts from (CFL number 1: h over
        the largest particle speed plus the fastest elastic wave speed of the particles' moduli,
        snow's hardened) warns, before stepping, with a RuntimeWarning naming dt and the limit
        (the explicit scheme's stability limit is only estimated by the CFL rule, so this is a
        warning, not an error: measured on a moving block at 1e5 Pa, nu 0.3, water runs
        diverge from CFL 1.2 on, elastic ones from 1.5, snow ones (whose hardened wave speed
        overstates its plastic stiffness) only from 5). Steps that stay beyond the limit warn
        again only when the CFL number dt / cfl_dt() has grown by 10% since the last warning
        (a run at a dt just beyond it warns once, not once per step); a step within the limit
        ends the run of warnings. The check costs no pass over the particles when the state is
        the one the last step left (no view alive, no particle added): that step measured the
        speeds as it wrote them. Raises DivergenceError on a blow-up."""
        return self._sim.step(self._check_dt(positive(dt, "dt")))

    def cfl_dt(self) -> float:
        """h / (v_max + c) [s]: the step of CFL number 1 at the current velocities, c the fastest
        elastic wave speed as in :meth:`stable_dt` (``stable_dt(cfl)`` is at most ``cfl`` times
        it); ``inf`` when nothing moves and nothing is stiff. Steps above it warn. After a step,
        with no view alive, it is read from what that step measured (the same value, bit for
        bit, as a pass over the particles)."""
        return self._sim.cfl_dt()

    def _check_dt(self, dt):
        """Warns when dt exceeds cfl_dt() (see step); returns dt."""
        limit = self._sim.cfl_dt()
        if not 0 < limit < dt:  # within (0 or NaN: a non-finite value written through a view, the step names it)
            self._warned_cfl = 0.0
            return dt
        cfl = dt / limit
        if cfl > 1.1 * self._warned_cfl:  # a new run of steps beyond the limit, or 10% further beyond
            self._warned_cfl = cfl
            warnings.warn(f"dt: {dt:.4g} s exceeds cfl_dt() = {limit:.4g} s (h / (v_max + c), CFL number 1, "
                          f"the explicit MPM step's estimated stability limit; CFL number {cfl:.3g}, "
                          f"stable_dt() = {self.stable_dt():.4g} s): the run may diverge (warned again only "
                          "if the CFL number grows 10% further)", RuntimeWarning, stacklevel=user_stacklevel())
        return dt

    def advance(self, duration, cfl=0.5) -> int:
        """Steps of :meth:`stable_dt` until ``duration`` [s] has passed (the last step lands on
        the end; a sliver under a tenth of a step is absorbed by the one before); returns the
        number of steps. The :class:`StepStats` of the last step (stage and wall seconds summed
        over all) are in :attr:`last_stats`. ``cfl`` above 1 warns (RuntimeWarning): its steps
        may exceed :meth:`cfl_dt`, the estimated stability limit (see :meth:`step`)."""
        cfl = positive(cfl, "cfl")
        if cfl > 1:
            warnings.warn(f"cfl: {cfl:.4g} > 1 lets advance's steps exceed cfl_dt() (CFL number 1), the explicit "
                          "MPM step's estimated stability limit: the run may diverge", RuntimeWarning,
                          stacklevel=user_stacklevel())
        steps, self.last_stats = self._sim.advance(non_negative(duration, "duration"), cfl)
        return steps

    def stable_dt(self, cfl=0.5) -> float:
        """min(cfl h / (v_max + c), sqrt(cfl h / |g|), max_dt) with c the fastest elastic wave
        speed (sqrt((lambda + 2 mu)/rho), water sqrt(K/rho)) of the materials present."""
        return self._sim.stable_dt(positive(cfl, "cfl"))

    # ---------------------------------------------------------------- diagnostics
    def kinetic_energy(self) -> float:
        """sum m |v|^2 / 2 [J]."""
        return finite_result(self._sim.kinetic_energy(), "kinetic_energy")

    def momentum(self) -> np.ndarray:
        """sum m v, shape (d,) [kg m/s]."""
        return finite_result(np.array(self._sim.momentum()), "momentum")

    def angular_momentum(self):
        """The angular momentum about the origin that APIC conserves: sum m x x v plus each
        particle's affine part m h^2/4 eps:C^T. A float in 2D, shape (3,) in 3D."""
        L = self._sim.angular_momentum()
        return float(L[0]) if self.dim == 2 else np.array(L)

    @property
    def materials(self) -> list:
        """One :class:`kinema._core.mpm.Material` per add_particles call (kind, density,
        youngs_modulus, poisson_ratio, mu, lambda_ ...); the ``material`` codes index it."""
        return self._sim.materials

    @property
    def config(self) -> Config:
        """A copy of the solver's :class:`Config` (gravity, max_cells_per_step, max_dt)."""
        return self._sim.config

    @property
    def count(self) -> int:
        return self._sim.count

    x = property(lambda self: self._sim.x, doc="(n, d) positions [m], writable view")
    v = property(lambda self: self._sim.v, doc="(n, d) velocities [m/s], writable view")
    F = property(lambda self: self._sim.F, doc="(n, d, d) elastic deformation gradients, writable view")
    C = property(lambda self: self._sim.C, doc="(n, d, d) APIC affine matrices [1/s], writable view")
    mass = property(lambda self: self._sim.mass, doc="(n,) masses [kg], writable view")
    volume = property(lambda self: self._sim.volume, doc="(n,) rest volumes [m^d], writable view")
    material = property(lambda self: self._sim.material, doc="(n,) material codes (index into materials)")
    Jp = property(lambda self: self._sim.Jp, doc="(n,) plastic volume ratios, writable view")
    youngs_modulus = property(lambda self: self._sim.youngs_modulus,
                              doc="(n,) per-particle Young's modulus [Pa] (water: bulk modulus), writable view")
    poisson_ratio = property(lambda self: self._sim.poisson_ratio,
                             doc="(n,) per-particle Poisson ratio, writable view")

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._sim.time

    @time.setter
    def time(self, t):
        self._sim.time = finite(t, "time")

    # ---------------------------------------------------------------- checkpoints
    _STATE_ARRAYS = ("x", "v", "F", "C", "mass", "volume", "material", "Jp", "youngs_modulus", "poisson_ratio")

    @property
    def parameters(self) -> tuple:
        """Names of the differentiable parameters, per particle: ``youngs_modulus`` and
        ``poisson_ratio`` ((n,) arrays)."""
        return ("youngs_modulus", "poisson_ratio")

    def state(self) -> dict:
        """Copies of everything that evolves (the particle arrays, time and step count)."""
        out = {k: getattr(self._sim, k).copy() for k in self._STATE_ARRAYS}
        out["time"] = np.float64(self._sim.time)
        out["steps"] = np.int64(self._sim.steps)
        return out

    def set_state(self, state: dict):
        """Restores :meth:`state`'s dict exactly (same particle count and materials). Every
        entry is checked before anything is written: a refused dict leaves the state as it was."""
        if not isinstance(state, dict):
            raise ValueError(f"state: expected a dict from state(), got {type(state).__name__}")
        values = {}
        for k in self._STATE_ARRAYS:
            if k not in state:
                raise ValueError(f"state: missing '{k}'")
            view = getattr(self._sim, k)
            if k == "material":
                value = np.asarray(state[k])
                if value.dtype.kind not in "iu":
                    raise ValueError(f"state['material']: expected integer codes, got dtype {value.dtype}")
            else:
                value = as_float_array(state[k], f"state['{k}']")
            if value.shape != view.shape:
                raise ValueError(f"state['{k}']: expected shape {view.shape}, got {value.shape}")
            if k == "material" and (value.min(initial=0) < 0 or value.max(initial=0) >= len(self.materials)):
                raise ValueError(f"state['material']: codes must index the {len(self.materials)} materials")
            values[k] = value
        time = finite(state.get("time", 0.0), "state['time']")
        steps = integer(state.get("steps", 0), "state['steps']", low=0)
        for k, value in values.items():
            getattr(self._sim, k)[...] = value
        self._sim.time = time
        self._sim.steps = steps

    # ---------------------------------------------------------------- km.diff protocol
    _diff_state_names = ("x", "v", "F", "C")

    @staticmethod
    def _no_step_options(step_options):
        for option in step_options:
            raise ValueError(f"{option}: km.mpm.Simulation.step takes no option besides dt")

    def _diff_check(self, wrt, step_options):
        self._no_step_options(step_options)
        allowed = self._diff_state_names + self.parameters + ("controls",)
        for name in wrt:
            if name not in allowed:
                raise ValueError(f"wrt: {name!r} is not differentiable in km.mpm (expected one of {allowed})")
        codes = np.unique(self.material)
        kinds = [self.materials[c].kind for c in codes]
        refused = sorted({k for k in kinds if k not in ("elastic", "neohookean", "water")})
        if refused:
            raise ValueError(f"material: gradients need 'elastic', 'neohookean' or 'water' particles, the simulation "
                             f"has {refused} (their return mappings clamp singular values: see docs/guide/mpm.md)")

    def _diff_control_shape(self):
        return (self.count, self.dim)

    def _diff_get(self, name):
        if name not in self._diff_state_names + self.parameters:
            raise ValueError(f"name: {name!r} is not a state array or parameter of km.mpm.Simulation")
        return getattr(self._sim, name).copy()

    def _diff_set(self, name, value):
        if name not in self._diff_state_names + self.parameters:
            raise ValueError(f"name: {name!r} is not a state array or parameter of km.mpm.Simulation")
        view = getattr(self._sim, name)
        value = np.asarray(value, dtype=float)
        if value.shape != view.shape:
            raise ValueError(f"{name}: expected shape {view.shape}, got {value.shape}")
        view[...] = value

    def _control(self, control):
        if control is None:
            return None
        f = as_float_array(control, "controls")
        if f.shape != (self.count, self.dim):
            raise ValueError(f"controls: expected one step's forces of shape {(self.count, self.dim)} [N], "
                             f"got {f.shape}")
        return f

    def _diff_step(self, dt, control, step_options):
        self._no_step_options(step_options)
        return self._sim.step(self._check_dt(positive(dt, "dt")), self._control(control))

    def _diff_step_adjoint(self, dt, before, after, control, grad_after, step_options):
        grads = {k: as_float_array(grad_after[k], f"grads['{k}']") for k in self._diff_state_names if k in grad_after}
        grad_before, g_e, g_nu, g_control = self._sim.step_adjoint(positive(dt, "dt"), before, after,
                                                                   self._control(control), grads)
        return grad_before, {"youngs_modulus": g_e, "poisson_ratio": g_nu}, g_control

    def __repr__(self):
        return (f"kinema.mpm.Simulation(shape={self.shape}, h={self.h}, particles={self.count}, "
                f"materials={[m.kind for m in self.materials]}, t={self.time:.4g})")
