"""Self-gravitating particles: kick-drift-kick leapfrog with fast-multipole gravity.

    a_i = -G sum_{j != i} m_j (x_i - x_j) / (|x_i - x_j|^2 + s^2)^{3/2}      (Plummer softening s)

Forces come from the 3D FMM of :func:`kinema.fmm.laplace3d` (C++, GIL released, Ctrl-C
checked): the far field is the unsoftened 1/r expansion (relative accuracy ``eps``) and the
near field, every pair in adjacent leaves, is summed directly with the softened kernel. The
leaves are never narrower than ``20 s``, so a pair that sees the unsoftened far field is at
least 20 s apart, where softening changes its force by less than 3 s^2 / (2 r^2) < 0.4 % and
decays as 1/r^2 (the API contract; with s = 0 the forces are exact to eps). Up to
N = 1414 (2e6 pairs) the softened sum is done directly, exactly.

Time integration: the symplectic kick-drift-kick leapfrog (Hockney & Eastwood 1988), second
order, with a bounded energy error for a fixed step; momentum is conserved to the force's
accuracy (exactly by the direct sum, to ~eps by the FMM). No stability limit is checked: the
leapfrog's, dt < 2 / omega with omega^2 the largest tidal eigenvalue (up to G sum_j m_j / s^3
where mass crowds within s), is a property of the configuration, not of the system; choose dt
from the closest encounters expected. A blow-up raises km.DivergenceError.
"""

from __future__ import annotations

import time as _time

import numpy as np

from kinema import _core, _stepping, fmm
from kinema._checks import (
    as_float_array, checked_state, finite_result, integer, non_negative, positive, representable,
    simulation_object, spacing)
from kinema.errors import DivergenceError

__all__ = ["System", "plummer"]

_DIRECT_PAIRS = 2_000_000
# Leaves are at least this many softening lengths wide (see the module docstring).
_NEAR_WIDTH = 20.0

# Largest Plummer sphere drawn (about 10 GB of float64 arrays; the rejection loop is not
# interruptible).
MAX_PLUMMER = 10**8


@simulation_object
class System:
    """N self-gravitating particles.

    x: (N, 3) positions [m], v: (N, 3) velocities [m/s] (writable arrays, the state); N = 0
    is a valid system (steps change nothing, energies are 0).
    mass: (N,) masses [kg] or one for all. G: gravitational constant [m^3 kg^-1 s^-2].
    softening: Plummer length s [m] (phi = -G m / sqrt(r^2 + s^2)). eps: relative accuracy of
    the FMM's far field.
    Attributes: x, v, mass, time [s], steps (count), G, softening, eps.
    """

    parameters = ("mass", "G", "softening")

    def __init__(self, x, v, mass, *, G=1.0, softening=0.0, eps=1e-8):
        x = as_float_array(x, "x", ndim=2)
        if x.shape[1] != 3:  # N = 0 is a valid (empty) system: steps change nothing
            raise ValueError(f"x: expected shape (n, 3), got {x.shape}")
        v = as_float_array(v, "v", ndim=2)
        if v.shape != x.shape:
            raise ValueError(f"v: expected shape {x.shape} (as x), got {v.shape}")
        m = as_float_array(mass, "mass")
        if np.ndim(mass) == 0:  # as_float_array makes a scalar a 1-element array
            m = np.full(len(x), float(m[0]))
        if m.shape != (len(x),):
            raise ValueError(f"mass: expected a scalar or shape ({len(x)},), got {m.shape}")
        if (m < 0).any():
            raise ValueError("mass: expected masses >= 0")
        self.x = x.copy()
        self.v = v.copy()
        self.mass = m.copy()
        self.G = positive(G, "G")
        self.softening = non_negative(softening, "softening")
        self.eps = fmm._eps(eps)
        self.time = 0.0
        self.steps = 0
        self._acc = None  # a(x) at the current positions, reused by the next step's first kick

    # ------------------------------------------------------------------ forces
    def _field(self, derivatives):
        """(N, width) potential [and gradient] per unit G; with s = 0 raises km.DivergenceError
        when particles of nonzero mass coincide (the C++ near field counts those pairs)."""
        n = len(self.x)
        direct = n * n <= _DIRECT_PAIRS
        kernel = "plummer" if self.softening > 0 else "laplace"
        out, info = fmm._eval3d(self.x, self.mass, None, eps=self.eps, derivatives=derivatives,
                                kernel=kernel, length=self.softening,
                                min_width=_NEAR_WIDTH * self.softening, direct=direct)
        if self.softening == 0 and info["coincident"] > 0:
            what = "accelerations" if derivatives else "potential_energy"
            raise DivergenceError(f"{what}: particles coincide at step {self.steps} "
                                  f"(t = {self.time:g}), an infinite force and energy without "
                                  "softening; give softening > 0")
        return out[:, 0, :]

    def accelerations(self) -> np.ndarray:
        """a_i (N, 3) [m/s^2] at the current positions.

        With s = 0, particles of nonzero mass at the same position, or so close that a force
        exceeds the float range, raise km.DivergenceError (a massless particle exactly on
        another feels nothing from it)."""
        a = self.G * self._field(1)[:, 1:4]
        if not np.isfinite(a).all():
            raise DivergenceError(f"accelerations: non-finite at step {self.steps} (t = {self.time:g}); "
                                  "particles this close need softening > 0")
        return a

    def potential_energy(self) -> float:
        """-G/2 sum_i m_i sum_{j != i} m_j / sqrt(r_ij^2 + s^2) [J].

        Particles at the same position add -G m_i m_j / s (counted by the softened near field);
        with s = 0 their energy is infinite and a km.DivergenceError says so (a massless
        particle adds nothing)."""
        energy = -0.5 * self.G * np.dot(self.mass, self._field(0)[:, 0])
        return finite_result(float(energy), "potential_energy")

    def kinetic_energy(self) -> float:
        """1/2 sum_i m_i |v_i|^2 [J]."""
        return finite_result(float(0.5 * np.dot(self.mass, np.einsum("ij,ij->i", self.v, self.v))),
                             "kinetic_energy")

    def energy(self) -> float:
        """Kinetic plus (softened) potential energy, self terms left out [J]."""
        return self.kinetic_energy() + self.potential_energy()

    def momentum(self) -> np.ndarray:
        """sum_i m_i v_i (3,) [kg m/s]."""
        return finite_result(self.mass @ self.v, "momentum")

    def angular_momentum(self) -> np.ndarray:
        """sum_i m_i x_i x v_i (3,) [kg m^2/s], about the origin."""
        return finite_result(self.mass @ np.cross(self.x, self.v), "angular_momentum")

    def virial_ratio(self) -> float:
        """2 K / |W| (1 in virial equilibrium)."""
        w = abs(self.potential_energy())
        if w == 0:
            raise ValueError("virial_ratio: the potential energy is zero (fewer than two particles, or no mass)")
        return 2 * self.kinetic_energy() / w

    # ------------------------------------------------------------------ time stepping
    def step(self, dt) -> _core.StepStats:
        """One kick-drift-kick leapfrog step of dt [s]; returns its km StepStats (time at the
        end [s], dt [s], wall seconds). A step that fails (km.DivergenceError, Ctrl-C) leaves
        the state as it was before it, so a smaller dt can be tried at once."""
        dt = positive(dt, "dt")
        start = _time.perf_counter()
        before = self.state()
        try:
            self._leapfrog(dt)
        except BaseException:
            self.set_state(before)
            raise
        return _core.StepStats(time=self.time, dt=dt, seconds=_time.perf_counter() - start)

    def _leapfrog(self, dt):
        if self._acc is None:
            self._acc = self.accelerations()
        self.v += 0.5 * dt * self._acc
        self.x += dt * self.v
        self._acc = self.accelerations()
        self.v += 0.5 * dt * self._acc
        self.time += dt
        self.steps += 1
        if not (np.isfinite(self.x).all() and np.isfinite(self.v).all()):
            raise DivergenceError(f"positions/velocities: non-finite at step {self.steps} "
                                  f"(t = {self.time:g}); reduce dt (now {dt:g}) or add softening")

    def advance(self, duration, dt, *, callback=None):
        """Steps of dt up to `duration` [s], the last landing on it (a remainder under dt/10 is
        absorbed by stretching the last step, the rule of every method).

        callback(system), if given, runs after every step (progress output, recording)."""
        return _stepping.advance(self, duration, dt, callback)

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        """Copies of everything that evolves: x, v, time, steps and the cached acceleration."""
        s = {"x": self.x.copy(), "v": self.v.copy(), "time": np.array(self.time),
             "steps": np.array(self.steps)}
        if self._acc is not None:
            s["a"] = self._acc.copy()
        return s

    def set_state(self, state: dict) -> None:
        """Restores a :meth:`state` exactly (the resumed run is bitwise the uninterrupted one).
        A refused dict (missing keys, wrong shapes, non-finite values) changes nothing."""
        x, v, time, steps = checked_state(state, ("x", "v"), self.x.shape)
        acc = None
        if "a" in state:
            acc = as_float_array(state["a"], "state['a']")
            if acc.shape != self.x.shape:
                raise ValueError(f"state['a']: expected shape {self.x.shape}, got {acc.shape}")
        self.x[...] = x
        self.v[...] = v
        self.time, self.steps, self._acc = time, steps, acc


def plummer(n, *, seed=0, G=1.0, total_mass=1.0, scale=1.0):
    """A Plummer sphere in virial equilibrium (Aarseth, Henon & Wielen 1974, A&A 37:183).

    n particles of equal mass total_mass/n; `scale` is the Plummer radius a. Radii from the
    inverted cumulative mass, speeds by von Neumann rejection from the isotropic distribution
    function (q^2 (1 - q^2)^{7/2}, q = v / v_escape). Returned in the centre-of-mass frame:
    (x (n, 3) [m], v (n, 3) [m/s], mass (n,) [kg]).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"n: expected an integer >= 2, got {n!r}")
    integer(n, "n", high=MAX_PLUMMER)
    if seed is not None:
        integer(seed, "seed", low=0)
    G = positive(G, "G")
    total_mass = positive(total_mass, "total_mass")
    a = spacing(scale, "scale")
    rng = np.random.default_rng(seed)

    def directions(k):
        d = rng.standard_normal((k, 3))
        return d / np.linalg.norm(d, axis=1)[:, None]

    # Radii: M(r)/M = r^3 / (r^2 + a^2)^{3/2}; the outermost 0.1 % of the mass is re-drawn
    # (r < 31.6 a), as AHW's cut keeps a few particles from flying to infinity.
    u = rng.uniform(0, 0.999, n)
    with np.errstate(all="ignore"):  # a scale near the float64 limits: checked below
        r = a / np.sqrt(u ** (-2.0 / 3.0) - 1.0)
    x = directions(n) * r[:, None]
    q = np.empty(n)
    todo = np.arange(n)
    while len(todo):
        qs = rng.uniform(0, 1, len(todo))
        ys = rng.uniform(0, 0.1, len(todo))
        ok = ys < qs**2 * (1 - qs**2) ** 3.5
        q[todo[ok]] = qs[ok]
        todo = todo[~ok]
    with np.errstate(all="ignore"):
        v_escape = np.sqrt(2 * G * total_mass) * (r**2 + a**2) ** -0.25
        v = directions(n) * (q * v_escape)[:, None]
        mass = np.full(n, total_mass / n)
        x -= mass @ x / total_mass
        v -= mass @ v / total_mass
    for out in (x, v, mass):
        representable(out, "G, total_mass, scale", "the sphere's positions or velocities")
    return x, v, mass
