"""Taichi peer of bench/sph/diff_sph_bench.py: the same WCSPH droplet's gradient by Taichi's kernel
autodiff (ti.ad.Tape) on the CPU backend, written here for this task in the manner of Taichi's
own differentiable SPH example (python/taichi/examples/autodiff/diff_sph: every step's state in
its own slice of a (steps + 1, n) field, all particle pairs visited by every particle, no
neighbour grid), with kinema's physics: the cubic spline kernel of support 2 spacing, Tait's
equation of state with negative pressures clamped, the symmetric pressure force, the laminar
viscosity of kinema's kernels.h, gravity, per-step particle forces and symplectic Euler (no
walls). Loss L = sum_i w_i . x_i(T) / n. Run in its own process:

    .venv/bin/python bench/sph/diff_sph_taichi_peer.py TASK.npz DT --threads T [--fp f64]

Prints one JSON line: seconds per gradient (forward + backward, best of 2 after a warm-up that
compiles the kernels), the forward alone, and the directional derivative of L along the task's
direction of the initial velocities next to its own central differences (e = 1e-4, 1e-5, 1e-6 in
float64, 1e-2 in float32; the one closest to the adjoint as "fd").
"""

import argparse
import json
import math
import time

import numpy as np
import taichi as ti


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("task")
    ap.add_argument("dt", type=float)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fp", default="f64", choices=("f32", "f64"))
    ap.add_argument("--speed-of-sound", type=float, default=10.0)
    ap.add_argument("--viscosity", type=float, default=1e-4)
    ap.add_argument("--spacing", type=float, default=0.01)
    ap.add_argument("--rho0", type=float, default=1000.0)
    ap.add_argument("--gamma", type=float, default=7.0)
    a = ap.parse_args()
    fp = ti.f64 if a.fp == "f64" else ti.f32
    ti.init(arch=ti.cpu, cpu_max_num_threads=a.threads, default_fp=fp, random_seed=0, offline_cache=True)
    data = np.load(a.task)
    x0, v0, forces_np, weights_np, direction = (data[k] for k in ("x0", "v0", "forces", "weights", "direction"))
    steps, n, d = forces_np.shape
    dt = a.dt
    h = 2 * a.spacing
    rho0, gamma, nu = a.rho0, a.gamma, a.viscosity
    m = rho0 * a.spacing ** d
    B = rho0 * a.speed_of_sound ** 2 / gamma
    sigma = 40 / (7 * math.pi * h * h) if d == 2 else 8 / (math.pi * h ** 3)
    g = ti.Vector([0.0, -9.81, 0.0][:d], fp)
    vec = ti.types.vector(d, fp)

    x = ti.Vector.field(d, fp, (steps + 1, n), needs_grad=True)
    v = ti.Vector.field(d, fp, (steps + 1, n), needs_grad=True)
    rho = ti.field(fp, (steps, n), needs_grad=True)
    P = ti.field(fp, (steps, n), needs_grad=True)
    acc = ti.Vector.field(d, fp, (steps, n), needs_grad=True)
    force = ti.Vector.field(d, fp, (steps, n), needs_grad=True)
    w = ti.Vector.field(d, fp, n)
    loss = ti.field(fp, (), needs_grad=True)

    @ti.func
    def kernel_w(r):
        q = r / h
        res = 0.0
        if q < 1:
            if q <= 0.5:
                res = sigma * (6 * (q * q * q - q * q) + 1)
            else:
                res = sigma * 2 * (1 - q) ** 3
        return res

    @ti.func
    def grad_factor(r):  # dW/dr / r
        q = r / h
        res = 0.0
        if 0 < q < 1:
            if q <= 0.5:
                res = sigma / h * 6 * (3 * q * q - 2 * q) / r
            else:
                res = -sigma / h * 6 * (1 - q) ** 2 / r
        return res

    @ti.kernel
    def clear(t: ti.i32):
        for i in range(n):
            rho[t, i] = m * sigma
            acc[t, i] = g + force[t, i] / m

    @ti.kernel
    def density(t: ti.i32):
        for i, j in ti.ndrange(n, n):
            if i != j:
                r = (x[t, i] - x[t, j]).norm()
                if r < h:
                    rho[t, i] += m * kernel_w(r)

    @ti.kernel
    def pressure(t: ti.i32):
        for i in range(n):
            ratio = rho[t, i] / rho0
            p = 0.0
            if ratio > 1:
                p = B * (ratio ** gamma - 1)
            P[t, i] = p / (rho[t, i] * rho[t, i])

    @ti.kernel
    def accelerations(t: ti.i32):
        for i, j in ti.ndrange(n, n):
            if i != j:
                xij = x[t, i] - x[t, j]
                r2 = xij.dot(xij)
                if r2 < h * h:
                    r = ti.sqrt(r2)
                    gw = grad_factor(r) * xij
                    vij = v[t, i] - v[t, j]
                    visc = 2 * (d + 2) * nu * (m / rho[t, j]) * vij.dot(xij) / (r2 + 0.01 * h * h)
                    acc[t, i] += (visc - m * (P[t, i] + P[t, j])) * gw

    @ti.kernel
    def integrate(t: ti.i32):
        for i in range(n):
            v[t + 1, i] = v[t, i] + dt * acc[t, i]
            x[t + 1, i] = x[t, i] + dt * v[t + 1, i]

    @ti.kernel
    def compute_loss():
        for i in range(n):
            loss[None] += w[i].dot(x[steps, i]) / n

    x.from_numpy(np.broadcast_to(x0, (steps + 1, n, d)).copy())
    force.from_numpy(forces_np)
    w.from_numpy(weights_np)

    def set_velocity(v_init):
        v.from_numpy(np.broadcast_to(v_init, (steps + 1, n, d)).copy())
        loss[None] = 0

    def forward(v_init=None):
        if v_init is not None:
            set_velocity(v_init)
        for t in range(steps):
            clear(t)
            density(t)
            pressure(t)
            accelerations(t)
            integrate(t)
        compute_loss()

    def gradient():
        set_velocity(v0)  # outside the tape: the tape differentiates the steps and the loss
        with ti.ad.Tape(loss=loss):
            forward()
        return v.grad.to_numpy()[0]

    gradient()  # compile
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        gv = gradient()
        times.append(time.perf_counter() - t0)
    fwd = []
    for _ in range(2):
        t0 = time.perf_counter()
        forward(v0)
        ti.sync()
        fwd.append(time.perf_counter() - t0)
    fds = {}
    for e in ((1e-4, 1e-5, 1e-6) if a.fp == "f64" else (1e-2,)):
        forward(v0 + e * direction)
        lp = loss[None]
        forward(v0 - e * direction)
        lm = loss[None]
        fds[e] = (lp - lm) / (2 * e)
    adjoint = float((gv * direction).sum())
    fd = min(fds.values(), key=lambda f: abs(f - adjoint))  # the best agreement of the steps tried
    forward(v0)
    l0 = loss[None]
    print(json.dumps({"gradient_seconds": min(times), "forward_seconds": min(fwd), "loss": l0,
                      "adjoint": adjoint, "fd": fd, "fds": {str(k): f for k, f in fds.items()}}))


if __name__ == "__main__":
    main()
