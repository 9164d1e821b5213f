"""A straightforward Taichi CPU WCSPH, the peer of kinema's WCSPH in bench/sph/sph_bench.py.

Written here from the course formulas (Koschier et al. 2019; Becker and Teschner 2007), not
copied from any project: cubic spline kernel with support h = 2 * spacing, density by summation
over fluid and boundary samples (boundary volumes psi_b given, Akinci et al. 2012), Tait's
equation of state clamped at zero, the symmetric pressure force with pressure mirroring at the
boundary, gravity, symplectic Euler and a clamp into the domain box. Neighbours come from a
uniform grid of cell size h with a fixed capacity per cell, rebuilt every step. float32, as a
typical Taichi SPH is written.
"""


import math

import numpy as np

_ti = None


def _taichi(threads: int):
    global _ti
    if _ti is None:
        import taichi as ti

        ti.init(arch=ti.cpu, default_fp=ti.f32, cpu_max_num_threads=threads, log_level=ti.ERROR,
                offline_cache=True)
        _ti = ti
    return _ti


class TaichiWCSPH:
    """WCSPH in 3D on Taichi's CPU backend.

    x0: (n, 3) fluid positions; xb: (m, 3) boundary samples with volumes psi (rho0 V_b);
    spacing [m]; c speed of sound [m/s]; lower/upper: the domain box. cell_capacity: particles a
    grid cell may hold (a fuller cell raises, never drops particles silently).
    """

    def __init__(self, x0, xb, psi, spacing, c, lower, upper, *, rho0=1000.0, gamma=7.0,
                 gravity=(0.0, -9.81, 0.0), threads=2, cell_capacity=48):
        ti = _taichi(threads)
        n, m = len(x0), len(xb)
        self.n, self.m = n, m
        h = 2.0 * spacing
        mass = rho0 * spacing**3
        sigma = 8.0 / (math.pi * h**3)
        B = rho0 * c * c / gamma
        lo = np.asarray(lower, float) - 3 * spacing
        hi = np.asarray(upper, float) + 3 * spacing
        dims = np.maximum(1, np.ceil((hi - lo) / h).astype(int))
        ncell = int(np.prod(dims))
        cap = cell_capacity

        self.x = ti.Vector.field(3, ti.f32, n)
        self.v = ti.Vector.field(3, ti.f32, n)
        self.a = ti.Vector.field(3, ti.f32, n)
        self.rho = ti.field(ti.f32, n)
        self.p = ti.field(ti.f32, n)
        self.bx = ti.Vector.field(3, ti.f32, max(m, 1))
        self.bpsi = ti.field(ti.f32, max(m, 1))
        self.count = ti.field(ti.i32, ncell)
        self.ids = ti.field(ti.i32, (ncell, cap))
        self.bcount = ti.field(ti.i32, ncell)
        self.bids = ti.field(ti.i32, (ncell, cap))
        self.overflow = ti.field(ti.i32, ())
        self.x.from_numpy(np.asarray(x0, np.float32))
        self.v.fill(0)
        if m:
            self.bx.from_numpy(np.asarray(xb, np.float32))
            self.bpsi.from_numpy(np.asarray(psi, np.float32))

        origin = ti.Vector(list(lo.astype(np.float32)))
        dim = ti.Vector(list(dims.astype(np.int32)))
        lower_t = ti.Vector([float(v) for v in lower])
        upper_t = ti.Vector([float(v) for v in upper])
        g = ti.Vector([float(v) for v in gravity])

        @ti.func
        def W(r):
            q = r / h
            w = 0.0
            if q <= 0.5:
                w = sigma * (6.0 * (q * q * q - q * q) + 1.0)
            elif q < 1.0:
                w = sigma * 2.0 * (1.0 - q) ** 3
            return w

        @ti.func
        def gradW(rij):
            r = rij.norm()
            q = r / h
            out = ti.Vector([0.0, 0.0, 0.0])
            if r > 1e-9 and q < 1.0:
                dw = 0.0
                if q <= 0.5:
                    dw = sigma / h * 6.0 * (3.0 * q * q - 2.0 * q)
                else:
                    dw = -sigma / h * 6.0 * (1.0 - q) ** 2
                out = dw / r * rij
            return out

        @ti.func
        def cell_of(p):
            c = ti.cast(ti.floor((p - origin) / h), ti.i32)
            return ti.max(0, ti.min(c, dim - 1))

        @ti.func
        def flat(c):
            return (c[0] * dim[1] + c[1]) * dim[2] + c[2]

        @ti.kernel
        def bin_boundary():
            for b in range(m):
                k = flat(cell_of(self.bx[b]))
                slot = ti.atomic_add(self.bcount[k], 1)
                if slot < cap:
                    self.bids[k, slot] = b
                else:
                    self.overflow[None] = 1

        @ti.kernel
        def bin_fluid():
            for k in self.count:
                self.count[k] = 0
            for i in range(n):
                k = flat(cell_of(self.x[i]))
                slot = ti.atomic_add(self.count[k], 1)
                if slot < cap:
                    self.ids[k, slot] = i
                else:
                    self.overflow[None] = 1

        @ti.kernel
        def density_pressure():
            for i in range(n):
                xi = self.x[i]
                ci = cell_of(xi)
                rho = mass * W(0.0)
                for off in ti.static(ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2)))):
                    c = ci + off
                    if (c >= 0).all() and (c < dim).all():
                        k = flat(c)
                        for s in range(ti.min(self.count[k], cap)):
                            j = self.ids[k, s]
                            if j != i:
                                rho += mass * W((xi - self.x[j]).norm())
                        for s in range(ti.min(self.bcount[k], cap)):
                            b = self.bids[k, s]
                            rho += self.bpsi[b] * W((xi - self.bx[b]).norm())
                self.rho[i] = rho
                self.p[i] = ti.max(0.0, B * ((rho / rho0) ** gamma - 1.0))

        @ti.kernel
        def accelerate(dt: ti.f32):
            for i in range(n):
                xi = self.x[i]
                ci = cell_of(xi)
                pi = self.p[i] / (self.rho[i] * self.rho[i])
                acc = g
                for off in ti.static(ti.grouped(ti.ndrange((-1, 2), (-1, 2), (-1, 2)))):
                    c = ci + off
                    if (c >= 0).all() and (c < dim).all():
                        k = flat(c)
                        for s in range(ti.min(self.count[k], cap)):
                            j = self.ids[k, s]
                            if j != i:
                                pj = self.p[j] / (self.rho[j] * self.rho[j])
                                acc -= mass * (pi + pj) * gradW(xi - self.x[j])
                        for s in range(ti.min(self.bcount[k], cap)):
                            b = self.bids[k, s]
                            acc -= 2.0 * self.bpsi[b] * pi * gradW(xi - self.bx[b])
                self.a[i] = acc
            for i in range(n):
                v = self.v[i] + dt * self.a[i]
                x = self.x[i] + dt * v
                for d in ti.static(range(3)):
                    if x[d] < lower_t[d]:
                        x[d] = lower_t[d]
                        v[d] = ti.max(v[d], 0.0)
                    if x[d] > upper_t[d]:
                        x[d] = upper_t[d]
                        v[d] = ti.min(v[d], 0.0)
                self.v[i] = v
                self.x[i] = x

        self._bin_fluid = bin_fluid
        self._density_pressure = density_pressure
        self._accelerate = accelerate
        self.bcount.fill(0)
        bin_boundary()
        self._check_overflow()

    def _check_overflow(self):
        if self.overflow[None]:
            raise RuntimeError("TaichiWCSPH: a grid cell overflowed its capacity; raise cell_capacity")

    def step(self, dt: float) -> None:
        self._bin_fluid()
        self._density_pressure()
        self._accelerate(dt)

    def sync(self) -> None:
        _ti.sync()
        self._check_overflow()

    def density_error(self, rho0=1000.0) -> float:
        """Mean compression max(rho/rho0 - 1, 0) of the densities the last step computed."""
        rho = self.rho.to_numpy().astype(np.float64)
        return float(np.maximum(rho / rho0 - 1, 0).mean())

    def positions(self) -> np.ndarray:
        return self.x.to_numpy().astype(np.float64)
