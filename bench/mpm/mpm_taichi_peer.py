"""Taichi peers of bench/mpm/mpm_bench.py: the algorithms of Taichi's shipped MPM examples (mpm88: 2D
weakly compressible fluid; mpm99: water, jelly and snow with SVD plasticity; mpm3d: 3D fluid),
written here from the published MLS-MPM algorithm (Hu et al. 2018), driven headless on the CPU
backend in float32 as the examples run. Run in its own process by mpm_bench.py:

    .venv/bin/python bench/mpm/mpm_taichi_peer.py {mpm88,mpm99,mpm3d} POSITIONS.npy STEPS DT GRID [--threads T]

Prints one JSON line: seconds per substep, wall and CPU (best of 3 blocks of STEPS substeps,
after a warm-up block that compiles the kernels) and the mean particle position afterwards (the bench checks
it against kinema's run from the same start).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import taichi as ti


def build(kind, x0, n_grid, dt, threads):
    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f32, random_seed=0, offline_cache=True)
    dim = x0.shape[1]
    n = x0.shape[0]
    dx = 1.0 / n_grid
    p_vol = (dx * 0.5) ** dim
    rho = 1.0
    p_mass = p_vol * rho
    bound = 3
    E, nu = (5e3, 0.2) if kind == "mpm99" else (400.0, 0.0)
    mu0, la0 = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    vec = ti.types.vector(dim, ti.f32)
    mat = ti.types.matrix(dim, dim, ti.f32)
    x = ti.Vector.field(dim, ti.f32, n)
    v = ti.Vector.field(dim, ti.f32, n)
    C = ti.Matrix.field(dim, dim, ti.f32, n)
    F = ti.Matrix.field(dim, dim, ti.f32, n)
    J = ti.field(ti.f32, n)
    Jp = ti.field(ti.f32, n)
    material = ti.field(ti.i32, n)
    grid_v = ti.Vector.field(dim, ti.f32, (n_grid,) * dim)
    grid_m = ti.field(ti.f32, (n_grid,) * dim)
    gravity = vec([0.0, -9.8] + [0.0] * (dim - 2))

    @ti.func
    def stress_of(p):
        # Kirchhoff stress tau (and the updated F for mpm99's plasticity).
        tau = mat(0.0)
        if ti.static(kind == "mpm99"):
            F[p] = (ti.Matrix.identity(ti.f32, dim) + dt * C[p]) @ F[p]
            h = ti.exp(10 * (1.0 - Jp[p]))
            if material[p] == 1:  # jelly
                h = 0.3
            mu, la = mu0 * h, la0 * h
            if material[p] == 0:  # water
                mu = 0.0
            U, sig, V = ti.svd(F[p])
            Jd = 1.0
            for d in ti.static(range(dim)):
                new_sig = sig[d, d]
                if material[p] == 2:  # snow
                    new_sig = ti.min(ti.max(sig[d, d], 1 - 2.5e-2), 1 + 4.5e-3)
                Jp[p] *= sig[d, d] / new_sig
                sig[d, d] = new_sig
                Jd *= new_sig
            if material[p] == 0:
                F[p] = ti.Matrix.identity(ti.f32, dim) * ti.sqrt(Jd)
            elif material[p] == 2:
                F[p] = U @ sig @ V.transpose()
            tau = 2 * mu * (F[p] - U @ V.transpose()) @ F[p].transpose() + \
                ti.Matrix.identity(ti.f32, dim) * la * Jd * (Jd - 1)
        else:
            tau = ti.Matrix.identity(ti.f32, dim) * (E * J[p] * (J[p] - 1))
        return tau

    @ti.kernel
    def substep():
        for I in ti.grouped(grid_m):
            grid_v[I] = vec(0.0)
            grid_m[I] = 0.0
        for p in x:
            Xp = x[p] / dx
            base = int(Xp - 0.5)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            affine = -dt * p_vol * 4 / dx ** 2 * stress_of(p) + p_mass * C[p]
            for offset in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                grid_v[base + offset] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + offset] += weight * p_mass
        for I in ti.grouped(grid_m):
            if grid_m[I] > 0:
                grid_v[I] /= grid_m[I]
            grid_v[I] += dt * gravity
            cond = (I < bound) & (grid_v[I] < 0) | (I > n_grid - bound) & (grid_v[I] > 0)
            grid_v[I] = ti.select(cond, 0, grid_v[I])
        for p in x:
            Xp = x[p] / dx
            base = int(Xp - 0.5)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = vec(0.0)
            new_C = mat(0.0)
            for offset in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                g_v = grid_v[base + offset]
                new_v += weight * g_v
                new_C += 4 * weight * g_v.outer_product(dpos) / dx ** 2
            v[p] = new_v
            x[p] += dt * v[p]
            J[p] *= 1 + dt * new_C.trace()
            C[p] = new_C

    x.from_numpy(x0.astype(np.float32))
    v.from_numpy(np.zeros_like(x0, dtype=np.float32))
    J.fill(1.0)
    Jp.fill(1.0)
    F.from_numpy(np.broadcast_to(np.eye(dim, dtype=np.float32), (n, dim, dim)).copy())
    if kind == "mpm99":
        material.from_numpy((np.arange(n) * 3 // n).astype(np.int32))
    return substep, x


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("kind", choices=["mpm88", "mpm99", "mpm3d"])
    ap.add_argument("positions")
    ap.add_argument("steps", type=int)
    ap.add_argument("dt", type=float)
    ap.add_argument("grid", type=int)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    x0 = np.load(a.positions)
    substep, x = build(a.kind, x0, a.grid, a.dt, a.threads)
    for _ in range(a.steps):  # warm-up: JIT compilation
        substep()
    ti.sync()
    best, best_cpu = float("inf"), float("inf")
    for _ in range(3):
        start, cpu = time.perf_counter(), time.process_time()
        for _ in range(a.steps):
            substep()
        ti.sync()
        best = min(best, (time.perf_counter() - start) / a.steps)
        best_cpu = min(best_cpu, (time.process_time() - cpu) / a.steps)
    xs = x.to_numpy()
    print(json.dumps({"seconds": best, "cpu_seconds": best_cpu, "mean": xs.mean(axis=0).tolist(), "finite": bool(np.isfinite(xs).all()),
                      "total_steps": 4 * a.steps}))


if __name__ == "__main__":
    main()
