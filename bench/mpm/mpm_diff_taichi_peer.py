"""Taichi peer of bench/mpm/mpm_diff_bench.py: DiffTaichi's diffmpm gradient (Hu et al. 2020) on the
CPU backend, written here from the published algorithm (MLS-MPM with fixed-corotated stress,
a grid cleared and rebuilt every step; reverse mode by Taichi's kernel autodiff, replaying each
step's P2G and grid update before calling the kernels' .grad in reverse, as diffmpm does).
Same task as kinema's: particles, grid, dt, steps, moduli, gravity, per-step particle forces;
loss L = mean x of the particles after the run. Run in its own process:

    .venv/bin/python bench/mpm/mpm_diff_taichi_peer.py POSITIONS.npy STEPS DT GRID --threads T [--fp f64]

Prints one JSON line: seconds per gradient (forward + backward, best of 3 after a warm-up that
compiles the kernels), the forward alone, and the directional derivative of L along a random
direction of the initial velocities next to its central difference (its own FD agreement).
"""


import argparse
import json
import time

import numpy as np
import taichi as ti


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("positions")
    ap.add_argument("steps", type=int)
    ap.add_argument("dt", type=float)
    ap.add_argument("grid", type=int)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fp", default="f64", choices=("f32", "f64"))
    ap.add_argument("--youngs-modulus", type=float, default=4e3)
    ap.add_argument("--poisson-ratio", type=float, default=0.2)
    ap.add_argument("--density", type=float, default=1000.0)
    a = ap.parse_args()
    fp = ti.f64 if a.fp == "f64" else ti.f32
    ti.init(arch=ti.cpu, cpu_max_num_threads=a.threads, default_fp=fp, random_seed=0, offline_cache=True)
    x0 = np.load(a.positions)
    n, steps, dt, n_grid = len(x0), a.steps, a.dt, a.grid
    dx = 1.0 / n_grid
    inv_dx = float(n_grid)
    p_vol = (dx * 0.5) ** 2
    p_mass = p_vol * a.density
    E, nu = a.youngs_modulus, a.poisson_ratio
    mu, la = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    mat = ti.types.matrix(2, 2, fp)

    x = ti.Vector.field(2, fp, (steps + 1, n), needs_grad=True)
    v = ti.Vector.field(2, fp, (steps + 1, n), needs_grad=True)
    C = ti.Matrix.field(2, 2, fp, (steps + 1, n), needs_grad=True)
    F = ti.Matrix.field(2, 2, fp, (steps + 1, n), needs_grad=True)
    force = ti.Vector.field(2, fp, (steps, n), needs_grad=True)
    grid_v_in = ti.Vector.field(2, fp, (n_grid + 3, n_grid + 3), needs_grad=True)
    grid_m_in = ti.field(fp, (n_grid + 3, n_grid + 3), needs_grad=True)
    grid_v_out = ti.Vector.field(2, fp, (n_grid + 3, n_grid + 3), needs_grad=True)
    loss = ti.field(fp, (), needs_grad=True)

    @ti.kernel
    def clear_grid():
        for i, j in grid_m_in:
            grid_v_in[i, j] = [0, 0]
            grid_m_in[i, j] = 0
            grid_v_out[i, j] = [0, 0]
            grid_v_in.grad[i, j] = [0, 0]
            grid_m_in.grad[i, j] = 0
            grid_v_out.grad[i, j] = [0, 0]

    @ti.func
    def stencil(xp):
        # Grid index shifted by one so that the ghost layer at -1 is index 0; quadratic
        # B-spline weights of the 3 nodes per axis (rows).
        g = xp * inv_dx + 1
        base = ti.cast(g - 0.5, ti.i32)
        fx = g - ti.cast(base, fp)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2])
        return base, fx, w

    @ti.kernel
    def p2g(s: ti.i32):
        for p in range(n):
            base, fx, w = stencil(x[s, p])
            Fp = F[s, p]
            J = Fp.determinant()
            r, _ = ti.polar_decompose(Fp)
            tau = 2 * mu * (Fp - r) @ Fp.transpose() + ti.Matrix.identity(fp, 2) * la * J * (J - 1)
            affine = -(dt * p_vol * 4 * inv_dx * inv_dx) * tau + p_mass * C[s, p]
            for i in ti.static(range(3)):
                for j in ti.static(range(3)):
                    offset = ti.Vector([i, j])
                    dpos = (ti.cast(offset, fp) - fx) * dx
                    weight = w[i, 0] * w[j, 1]
                    grid_v_in[base + offset] += weight * (p_mass * v[s, p] + dt * force[s, p] + affine @ dpos)
                    grid_m_in[base + offset] += weight * p_mass

    @ti.kernel
    def grid_op():
        for i, j in grid_m_in:
            vo = ti.Vector([0.0, 0.0], fp)
            if grid_m_in[i, j] > 0:
                vo = grid_v_in[i, j] / grid_m_in[i, j] + dt * ti.Vector([0.0, -9.81], fp)
            # Sticky walls on the nodes at and beyond the domain's sides (index 1 is x = 0).
            if i <= 1 or i >= n_grid + 1 or j <= 1 or j >= n_grid + 1:
                vo = ti.Vector([0.0, 0.0], fp)
            grid_v_out[i, j] = vo

    @ti.kernel
    def g2p(s: ti.i32):
        for p in range(n):
            base, fx, w = stencil(x[s, p])
            new_v = ti.Vector([0.0, 0.0], fp)
            new_C = mat(0.0)
            for i in ti.static(range(3)):
                for j in ti.static(range(3)):
                    dpos = ti.cast(ti.Vector([i, j]), fp) - fx
                    weight = w[i, 0] * w[j, 1]
                    gv = grid_v_out[base[0] + i, base[1] + j]
                    new_v += weight * gv
                    new_C += 4 * inv_dx * weight * gv.outer_product(dpos)
            v[s + 1, p] = new_v
            C[s + 1, p] = new_C
            x[s + 1, p] = x[s, p] + dt * new_v
            F[s + 1, p] = (ti.Matrix.identity(fp, 2) + dt * new_C) @ F[s, p]

    @ti.kernel
    def compute_loss():
        for p in range(n):
            loss[None] += x[steps, p][0] / n

    def initialise(v0):
        x.from_numpy(np.concatenate([x0[None], np.zeros((steps, n, 2))]).astype(np.float64 if a.fp == "f64" else np.float32))
        vv = np.zeros((steps + 1, n, 2))
        vv[0] = v0
        v.from_numpy(vv)
        FF = np.zeros((steps + 1, n, 2, 2))
        FF[:] = np.eye(2)
        F.from_numpy(FF)
        C.fill(0)
        loss[None] = 0

    def forward():
        for s in range(steps):
            clear_grid()
            p2g(s)
            grid_op()
            g2p(s)
        compute_loss()
        return loss[None]

    def backward():
        x.grad.fill(0)
        v.grad.fill(0)
        C.grad.fill(0)
        F.grad.fill(0)
        force.grad.fill(0)
        loss.grad[None] = 1
        compute_loss.grad()
        for s in reversed(range(steps)):
            clear_grid()
            p2g(s)
            grid_op()
            g2p.grad(s)
            grid_op.grad()
            p2g.grad(s)

    rng = np.random.default_rng(0)
    v0 = rng.normal(0, 0.1, (n, 2))
    force.from_numpy(rng.normal(0, 1e-4, (steps, n, 2)))
    initialise(v0)
    forward()
    backward()  # warm-up: compiles every kernel and its gradient
    best_grad, best_fwd = np.inf, np.inf
    for _ in range(3):
        initialise(v0)
        t0 = time.perf_counter()
        forward()
        t1 = time.perf_counter()
        backward()
        t2 = time.perf_counter()
        best_grad, best_fwd = min(best_grad, t2 - t0), min(best_fwd, t1 - t0)
    grad_v0 = v.grad.to_numpy()[0]
    direction = rng.normal(size=(n, 2))
    e = 1e-5 if a.fp == "f64" else 1e-2
    initialise(v0 + e * direction)
    lp = forward()
    initialise(v0 - e * direction)
    lm = forward()
    fd = (lp - lm) / (2 * e)
    print(json.dumps({"n": n, "steps": steps, "fp": a.fp, "gradient_seconds": best_grad, "forward_seconds": best_fwd,
                      "adjoint": float((grad_v0 * direction).sum()), "fd": float(fd),
                      "v0_seed": 0}))


if __name__ == "__main__":
    main()
