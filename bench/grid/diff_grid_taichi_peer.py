"""Taichi's autodiff (ti.ad.Tape) of a 2D smoke-control gradient in the manner of DiffTaichi's
smoke example (Hu et al. 2020, "smoke_taichi"): a collocated velocity grid, semi-Lagrangian
advection (Euler back-trace, bilinear), a fixed number of Jacobi iterations for the pressure,
every time level stored for the tape. Run in its own process by bench/grid/diff_grid_bench.py
on the task it writes to an .npz file; prints one JSON line.

    .venv/bin/python bench/grid/diff_grid_taichi_peer.py TASK.npz --threads 2 [--jacobi 50]

TASK.npz holds rho0 (n, n), controls (T, n, n, 2), weights (n, n), direction (T, n, n, 2), h, dt.
The loss is <weights, density_T>, the gradient dL/d(controls); reported: seconds per gradient
(forward + backward on the tape, after one warm-up call that compiles the kernels), and the
directional derivative along `direction` with its own central difference. Also what the
projection leaves of the divergence (computed here in NumPy from Taichi's fields after a plain
forward run with the task's controls): per step, the RMS of the divergence of the velocity before
the projection (Taichi's own `div` field) and after it (the same central-difference operator, with
the same wall rule, applied to the projected velocity v[t+1]; it equals the MAC divergence of the
face averages of the collocated velocity, the measure kinema's projection drives to zero), their
ratio, and the relative residual ||h^2 div - (sum of neighbours - 4 p)|| / ||h^2 div|| of the
Poisson equation the Jacobi sweeps solve, each averaged over the T steps; and the ratio the same
projection would leave with that equation solved exactly (SciPy's sparse LU): the floor of the
collocated discretization, whose central-difference gradient and divergence do not compose to the
five-point Laplacian the sweeps solve.
"""

import argparse
import json
import time

import numpy as np
import taichi as ti


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("task")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--jacobi", type=int, default=50)
    opts = ap.parse_args()
    data = np.load(opts.task)
    rho0, controls, weights, direction = data["rho0"], data["controls"], data["weights"], data["direction"]
    h, dt = float(data["h"]), float(data["dt"])
    ti.init(arch=ti.cpu, default_fp=ti.f64, cpu_max_num_threads=opts.threads, log_level=ti.ERROR)
    T, n = controls.shape[0], controls.shape[1]
    J = opts.jacobi
    v = ti.Vector.field(2, ti.f64, shape=(T + 1, n, n), needs_grad=True)
    va = ti.Vector.field(2, ti.f64, shape=(T, n, n), needs_grad=True)
    ctrl = ti.Vector.field(2, ti.f64, shape=(T, n, n), needs_grad=True)
    smoke = ti.field(ti.f64, shape=(T + 1, n, n), needs_grad=True)
    div = ti.field(ti.f64, shape=(T, n, n), needs_grad=True)
    p = ti.field(ti.f64, shape=(T, J + 1, n, n), needs_grad=True)
    W = ti.field(ti.f64, shape=(n, n))
    loss = ti.field(ti.f64, shape=(), needs_grad=True)

    @ti.func
    def clamp_index(i):
        return ti.max(0, ti.min(n - 1, i))

    @ti.func
    def bilerp(f: ti.template(), t: ti.i32, x, y):
        x = ti.max(0.0, ti.min(n - 1.0, x))
        y = ti.max(0.0, ti.min(n - 1.0, y))
        i, j = ti.min(int(ti.floor(x)), n - 2), ti.min(int(ti.floor(y)), n - 2)
        fx, fy = x - i, y - j
        return ((1 - fx) * (1 - fy) * f[t, i, j] + fx * (1 - fy) * f[t, i + 1, j]
                + (1 - fx) * fy * f[t, i, j + 1] + fx * fy * f[t, i + 1, j + 1])

    @ti.kernel
    def advect(t: ti.i32):
        for i, j in ti.ndrange(n, n):
            x = i - dt / h * v[t, i, j][0]
            y = j - dt / h * v[t, i, j][1]
            smoke[t + 1, i, j] = bilerp(smoke, t, x, y)
            va[t, i, j] = bilerp(v, t, x, y) + dt * ctrl[t, i, j]

    @ti.kernel
    def divergence(t: ti.i32):
        for i, j in ti.ndrange(n, n):
            # closed walls: the normal velocity beyond the box is the negative of the inside one
            vl = va[t, i - 1, j][0] if i > 0 else -va[t, i, j][0]
            vr = va[t, i + 1, j][0] if i < n - 1 else -va[t, i, j][0]
            vb = va[t, i, j - 1][1] if j > 0 else -va[t, i, j][1]
            vt = va[t, i, j + 1][1] if j < n - 1 else -va[t, i, j][1]
            div[t, i, j] = (vr - vl + vt - vb) / (2 * h)

    @ti.kernel
    def jacobi(t: ti.i32, k: ti.i32):
        for i, j in ti.ndrange(n, n):
            s = (p[t, k, clamp_index(i - 1), j] + p[t, k, clamp_index(i + 1), j]
                 + p[t, k, i, clamp_index(j - 1)] + p[t, k, i, clamp_index(j + 1)])
            p[t, k + 1, i, j] = (s - h * h * div[t, i, j]) / 4

    @ti.kernel
    def project(t: ti.i32):
        for i, j in ti.ndrange(n, n):
            gx = (p[t, J, clamp_index(i + 1), j] - p[t, J, clamp_index(i - 1), j]) / (2 * h)
            gy = (p[t, J, i, clamp_index(j + 1)] - p[t, J, i, clamp_index(j - 1)]) / (2 * h)
            v[t + 1, i, j] = va[t, i, j] - ti.Vector([gx, gy])

    @ti.kernel
    def compute_loss():
        for i, j in ti.ndrange(n, n):
            loss[None] += W[i, j] * smoke[T, i, j]

    W.from_numpy(weights)

    smoke_np = np.zeros((T + 1, n, n))
    smoke_np[0] = rho0

    def reset(c):  # outside the tape: these kernels are not differentiated
        ctrl.from_numpy(c)
        smoke.from_numpy(smoke_np)
        v.fill(0)
        p.fill(0)
        loss[None] = 0

    def forward():
        for t in range(T):
            advect(t)
            divergence(t)
            for k in range(J):
                jacobi(t, k)
            project(t)
        compute_loss()

    def gradient():
        reset(controls)
        with ti.ad.Tape(loss=loss):
            forward()
        return ctrl.grad.to_numpy(), loss[None]

    gradient()  # compiles the kernels
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        g, _ = gradient()
        times.append(time.perf_counter() - t0)
    e = 1e-4

    def value(c):
        reset(c)
        forward()
        return loss[None]

    fd = (value(controls + e * direction) - value(controls - e * direction)) / (2 * e)
    adj = float(np.sum(g * direction))
    value(controls)
    left = divergence_left(v.to_numpy(), va.to_numpy(), div.to_numpy(), p.to_numpy()[:, J], h)
    print(json.dumps({"gradient_seconds": min(times), "adjoint": adj, "fd": fd, "jacobi": J, **left}))


def central_divergence(vel, h):
    """The divergence kernel's operator in NumPy: central differences over 2h, the normal
    velocity beyond a closed wall the negative of the inside one."""
    vx, vy = vel[..., 0], vel[..., 1]
    px = np.concatenate([-vx[:1], vx, -vx[-1:]], axis=0)
    py = np.concatenate([-vy[:, :1], vy, -vy[:, -1:]], axis=1)
    return (px[2:] - px[:-2] + py[:, 2:] - py[:, :-2]) / (2 * h)


def clamped_laplacian(n):
    """The sweeps' operator as a sparse matrix: sum of the 4 clamped-index neighbours - 4 p."""
    import scipy.sparse as sp
    idx = np.arange(n * n).reshape(n, n)
    rows, cols = [idx.ravel()], [idx.ravel()]
    vals = [np.full(n * n, -4.0)]
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        i = np.clip(np.arange(n)[:, None] + di, 0, n - 1)
        j = np.clip(np.arange(n)[None, :] + dj, 0, n - 1)
        rows.append(idx.ravel()), cols.append(idx[i, j].ravel()), vals.append(np.ones(n * n))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * n, n * n))


def project_exactly(va, div, h, solve):
    """The project kernel's velocity with the sweeps' equation solved exactly (its right-hand
    side's mean removed: the operator's null space is the constants; one cell pinned)."""
    n = div.shape[0]
    b = h * h * div.ravel()
    b = b - b.mean()
    b[0] = 0.0
    p = solve(b).reshape(n, n)
    q = np.pad(p, 1, mode="edge")
    grad = np.stack([(q[2:, 1:-1] - q[:-2, 1:-1]) / (2 * h), (q[1:-1, 2:] - q[1:-1, :-2]) / (2 * h)], -1)
    return va - grad


def divergence_left(v, va, div, p, h):
    """Means over the steps of: RMS divergence before and after the projection [1/s], their
    ratio, the Jacobi sweeps' relative residual (clamped-index Neumann boundary), and the ratio
    left with that equation solved exactly."""
    import scipy.sparse.linalg as spla
    n = div.shape[1]
    A = clamped_laplacian(n).tolil()
    A[0, :] = 0.0
    A[0, 0] = 1.0
    solve = spla.factorized(A.tocsc())
    before, after, ratio, residual, exact = [], [], [], [], []
    for t in range(div.shape[0]):
        exact.append(np.sqrt(np.mean(central_divergence(project_exactly(va[t], div[t], h, solve), h) ** 2))
                     / np.sqrt(np.mean(div[t] ** 2)))
        d_after = central_divergence(v[t + 1], h)
        b, a = np.sqrt(np.mean(div[t] ** 2)), np.sqrt(np.mean(d_after ** 2))
        q = np.pad(p[t], 1, mode="edge")
        lap = q[:-2, 1:-1] + q[2:, 1:-1] + q[1:-1, :-2] + q[1:-1, 2:] - 4 * p[t]
        r = np.linalg.norm(h * h * div[t] - lap) / np.linalg.norm(h * h * div[t])
        before.append(b), after.append(a), ratio.append(a / b), residual.append(r)
    return {"div_before_rms": float(np.mean(before)), "div_after_rms": float(np.mean(after)),
            "div_left": float(np.mean(ratio)), "poisson_residual": float(np.mean(residual)),
            "div_left_exact_solve": float(np.mean(exact))}


if __name__ == "__main__":
    main()
