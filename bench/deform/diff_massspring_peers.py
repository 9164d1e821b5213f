"""The gradient of a mass-spring cloth run in Taichi (ti.ad.Tape) and NVIDIA Warp (wp.Tape), for
bench/deform/diff_massspring_bench.py, which runs this file in its own process per peer.

The task, the same in kinema: Taichi's cloth layout of bench/deform_bench.py ((N+1)^2 vertices in
[0.25, 0.75]^2, structural and shear springs, k = 1000, c = 0.5 along the springs, unit masses,
gravity (0, -2), the two corners N and (N+1)^2 - 1 pinned), `steps` symplectic Euler steps of dt
from rest (v0 = 0), loss L = sum_i w_i . x_i(T) for fixed random w;
the gradient dL/dv0. float64 throughout, CPU. Prints one JSON line: seconds per gradient
(forward + backward, best of --min-of; wall and CPU time of the process), the directional derivative along a random direction and
its central finite difference (h = 1e-5; bench/deform/diff_massspring_bench.py compares every
framework's directional derivative with the same difference of kinema's forward run).
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "common"))  # warp_tape.py
from warp_tape import TapeRun  # noqa: E402


def cloth(N):
    n1 = N + 1
    I, J = np.meshgrid(np.arange(n1), np.arange(n1), indexing="ij")
    idx = I * n1 + J
    x = np.stack([I.ravel(), J.ravel()], 1) * (0.5 / N) + 0.25

    def pairs(a, b):
        return np.stack([a.ravel(), b.ravel()], 1)
    springs = np.concatenate([pairs(idx[:-1, :], idx[1:, :]), pairs(idx[:, :-1], idx[:, 1:]),
                              pairs(idx[:-1, :-1], idx[1:, 1:]), pairs(idx[1:, :-1], idx[:-1, 1:])])
    rest = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    free = np.ones(len(x))
    free[[N, n1 * n1 - 1]] = 0
    return x, springs.astype(np.int32), rest, free


def inputs(N, seed=0):
    x, springs, rest, free = cloth(N)
    rng = np.random.default_rng(seed)
    rng.standard_normal(x.shape)  # the draw of kinema's problem(): the same w and direction follow
    v0 = np.zeros_like(x)  # from rest: a rough random v0 makes the run too sensitive for any FD
    w = rng.standard_normal(x.shape)
    direction = rng.standard_normal(x.shape) * free[:, None]
    return x, springs, rest, free, v0, w, direction


K, C, GX, GY = 1000.0, 0.5, 0.0, -2.0


def taichi_peer(N, steps, dt, threads):
    import taichi as ti
    ti.init(arch=ti.cpu, default_fp=ti.f64, cpu_max_num_threads=threads, offline_cache=True)
    x0, springs, rest, free, v0, w, direction = inputs(N)
    n, m = len(x0), len(springs)
    x = ti.Vector.field(2, ti.f64, shape=(steps + 1, n), needs_grad=True)
    v = ti.Vector.field(2, ti.f64, shape=(steps + 1, n), needs_grad=True)
    f = ti.Vector.field(2, ti.f64, shape=(steps, n), needs_grad=True)
    sp = ti.Vector.field(2, ti.i32, shape=m)
    L = ti.field(ti.f64, shape=m)
    fr = ti.field(ti.f64, shape=n)
    wf = ti.Vector.field(2, ti.f64, shape=n)
    loss = ti.field(ti.f64, shape=(), needs_grad=True)
    sp.from_numpy(springs)
    L.from_numpy(rest)
    fr.from_numpy(free)
    wf.from_numpy(w)

    @ti.kernel
    def forces(t: ti.i32):
        for s in range(m):
            i, j = sp[s][0], sp[s][1]
            d = x[t, j] - x[t, i]
            length = d.norm()
            nd = d / length
            fs = (K * (length - L[s]) + C * (v[t, j] - v[t, i]).dot(nd)) * nd
            f[t, i] += fs
            f[t, j] -= fs

    @ti.kernel
    def integrate(t: ti.i32):
        for i in range(n):
            vn = (v[t, i] + dt * (f[t, i] + ti.Vector([GX, GY]))) * fr[i]
            v[t + 1, i] = vn
            x[t + 1, i] = x[t, i] + dt * vn

    @ti.kernel
    def compute_loss():
        for i in range(n):
            loss[None] += wf[i].dot(x[steps, i])

    def start(vstart):
        # Outside the tape: a from_numpy or fill recorded on it would, reversed, clear the
        # gradient of the initial state it wrote.
        f.fill(0)
        loss[None] = 0
        xs = np.zeros((steps + 1, n, 2))
        xs[0] = x0
        vs = np.zeros((steps + 1, n, 2))
        vs[0] = vstart
        x.from_numpy(xs)
        v.from_numpy(vs)

    def forward():
        for t in range(steps):
            forces(t)
            integrate(t)
        compute_loss()

    def gradient():
        start(v0)
        with ti.ad.Tape(loss=loss):
            forward()
        return v.grad.to_numpy()[0]

    def value(vv):
        start(vv)
        forward()
        return loss[None]

    return run(gradient, value, v0, direction, threads)


def warp_peer(N, steps, dt, threads):
    import warp as wp
    wp.config.quiet = True
    wp.init()
    x0, springs, rest, free, v0, w, direction = inputs(N)
    n, m = len(x0), len(springs)
    dev = "cpu"

    @wp.kernel
    def forces(x: wp.array(dtype=wp.vec2d), v: wp.array(dtype=wp.vec2d), sp: wp.array(dtype=wp.int32, ndim=2),
               L: wp.array(dtype=wp.float64), f: wp.array(dtype=wp.vec2d)):
        s = wp.tid()
        i = sp[s, 0]
        j = sp[s, 1]
        d = x[j] - x[i]
        length = wp.length(d)
        nd = d / length
        fs = (wp.float64(K) * (length - L[s]) + wp.float64(C) * wp.dot(v[j] - v[i], nd)) * nd
        wp.atomic_add(f, i, fs)
        wp.atomic_sub(f, j, fs)

    @wp.kernel
    def integrate(x: wp.array(dtype=wp.vec2d), v: wp.array(dtype=wp.vec2d), f: wp.array(dtype=wp.vec2d),
                  fr: wp.array(dtype=wp.float64), h: wp.float64,
                  x_out: wp.array(dtype=wp.vec2d), v_out: wp.array(dtype=wp.vec2d)):
        i = wp.tid()
        vn = (v[i] + h * (f[i] + wp.vec2d(wp.float64(GX), wp.float64(GY)))) * fr[i]
        v_out[i] = vn
        x_out[i] = x[i] + h * vn

    sp = wp.array(springs, dtype=wp.int32, device=dev)
    Lw = wp.array(rest, dtype=wp.float64, device=dev)
    fr = wp.array(free, dtype=wp.float64, device=dev)
    h = wp.float64(dt)

    def step(x, v, f, x_out, v_out):
        wp.launch(forces, dim=m, inputs=[x, v, sp, Lw], outputs=[f], device=dev)
        wp.launch(integrate, dim=n, inputs=[x, v, f, fr, h], outputs=[x_out, v_out], device=dev)

    tape = TapeRun(wp, wp.vec2d, x0, w, steps, step, dev)
    return run(lambda: tape.gradient(v0), tape.forward, v0, direction, 1)


def run(gradient, value, v0, direction, threads, h=1e-5, min_of=3):
    gradient()  # compile / warm up
    times, cpu = [], []
    for _ in range(min_of):
        t, c = time.perf_counter(), time.process_time()
        g = gradient()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    t = time.perf_counter()
    value(v0)
    forward_seconds = time.perf_counter() - t
    fd = (value(v0 + h * direction) - value(v0 - h * direction)) / (2 * h)
    ad = float(np.sum(g * direction))
    return {"seconds": min(times), "cpu_seconds": min(cpu), "forward_seconds": forward_seconds, "directional": ad, "fd": fd,
            "fd_relative_error": abs(ad - fd) / abs(fd), "threads": threads}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("peer", choices=["taichi", "warp"])
    p.add_argument("N", type=int)
    p.add_argument("steps", type=int)
    p.add_argument("dt", type=float)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    fn = taichi_peer if args.peer == "taichi" else warp_peer
    print(json.dumps(fn(args.N, args.steps, args.dt, args.threads)), flush=True)


if __name__ == "__main__":
    main()
