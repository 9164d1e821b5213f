"""A small differentiable simulation in NumPy that implements km.diff's protocol, to test the
rollout machinery (checkpointing, chaining, controls, the torch bridge) apart from any solver.

Anharmonic oscillators, each particle in its own well: f = -k x - c |x|^2 x + u (u: control),
advanced by symplectic Euler: v' = v + dt f(x) / m, x' = x + dt v'. Parameters: stiffness k
(scalar or per particle), mass m (scalar or per particle), c (scalar).
"""

import numpy as np


class Oscillators:
    parameters = ("stiffness", "mass", "cubic")
    _diff_state_names = ("x", "v")

    def __init__(self, x, v, stiffness=3.0, mass=1.5, cubic=0.7):
        self.x = np.array(x, dtype=float)
        self.v = np.array(v, dtype=float)
        self.stiffness, self.mass, self.cubic = stiffness, mass, cubic
        self.time, self.step_count = 0.0, 0

    # km.diff protocol
    def state(self):
        return {"x": self.x.copy(), "v": self.v.copy(), "time": self.time, "step": self.step_count}

    def set_state(self, s):
        self.x[...] = s["x"]
        self.v[...] = s["v"]
        self.time, self.step_count = s["time"], s["step"]

    def _diff_check(self, wrt, options):
        if options.get("integrator", "symplectic") != "symplectic":
            raise ValueError(f"integrator: only 'symplectic' is differentiable, got {options['integrator']!r}")

    def _diff_control_shape(self):
        return self.x.shape

    def _diff_get(self, name):
        return getattr(self, name)

    def _diff_set(self, name, value):
        if name in ("x", "v"):
            getattr(self, name)[...] = value
        else:
            setattr(self, name, float(value) if np.ndim(value) == 0 else np.array(value, dtype=float))

    def _per_particle(self, a):
        return np.broadcast_to(np.asarray(a, dtype=float), self.x.shape[:1])[:, None]

    def _force(self, x, control):
        k, c = self._per_particle(self.stiffness), self.cubic
        f = -k * x - c * (x * x).sum(1, keepdims=True) * x
        return f if control is None else f + control

    def step(self, dt):
        self._diff_step(dt, None, {})

    def _diff_step(self, dt, control, options):
        self._diff_check((), options)
        self.v += dt * self._force(self.x, control) / self._per_particle(self.mass)
        self.x += dt * self.v
        self.time += dt
        self.step_count += 1

    def _diff_step_adjoint(self, dt, before, after, control, g, options):
        x = before["x"]
        m, k, c = self._per_particle(self.mass), self._per_particle(self.stiffness), self.cubic
        f = self._force(x, control)
        gv1 = g["v"] + dt * g["x"]            # x' = x + dt v'
        gf = dt * gv1 / m                     # v' = v + dt f / m
        r2 = (x * x).sum(1, keepdims=True)
        gx = g["x"] - k * gf - c * (r2 * gf + 2 * x * (x * gf).sum(1, keepdims=True))
        gk = -(x * gf).sum(1)
        gm = -(dt * gv1 * f).sum(1) / m[:, 0] ** 2
        gc = -float((r2 * x * gf).sum())
        params = {
            "stiffness": float(gk.sum()) if np.ndim(self.stiffness) == 0 else gk,
            "mass": float(gm.sum()) if np.ndim(self.mass) == 0 else gm,
            "cubic": gc,
        }
        return {"x": gx, "v": gv1}, params, (None if control is None else gf.copy())
