"""Time per gradient through the neo-Hookean cube's symplectic run: kinema (km.diff over
km.fem.Body) beside NVIDIA Warp (wp.Tape over the same tetrahedral FEM written as Warp kernels,
the pattern of Warp's soft-body examples, on its CPU device), at equal agreement with finite
differences.

The task: the cube of bench/deform/diff_fem_bench.py (20^3 vertices, 34,295 tetrahedra,
km.fem.box_mesh), the stable neo-Hookean of Smith, de Goes and Kim (2018) as kinema writes it
(cpp/fem/kernels.h: P = mu F + lam' (J - alpha) cof F, lam' = lam + mu, alpha = 1 + mu / lam'),
E = 5e4, nu = 0, rho = 1000 (kinema's lumped masses, handed to Warp), gravity -9.8 y, no
damping, an initial velocity with a shear; T symplectic Euler steps of dt = 1e-3
(v' = v + dt (f / m + g), x' = x + dt v'), float64 throughout; loss L = w . x_T for fixed random
w, gradient dL/dv0. Each code's directional derivative along a random direction is compared with
the central difference (h = 1e-5) of kinema's forward run: a Warp model that differed from
kinema's would show there.

    .venv/bin/python bench/deform/diff_fem_peers.py [--steps 100] [--n 20] [--min-of 3]

Warp runs in its own process (`--warp`); the last line printed is the one-line summary. For the
work each code does, run with OMP_NUM_THREADS=1 (Warp's CPU device uses one thread) and compare
the CPU times. No Taichi peer: bench/ has no Taichi soft-body gradient (deform_taichi_peer.py
runs Taichi's implicit_fem example forward only).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "common"))  # harness.py, warp_tape.py
import harness  # noqa: E402
from warp_tape import TapeRun  # noqa: E402

E, NU, RHO, G, DT = 5e4, 0.0, 1000.0, -9.8, 1e-3


def problem(n, seed=0):
    """The body (kinema), its initial velocity, the loss weights and a direction."""
    import kinema as km
    V, T = km.fem.box_mesh([0, 1, 0], [1, 2, 1], n - 1, tets_per_cell=5)
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=E, poisson_ratio=NU, density=RHO,
                       gravity=(0, G, 0))
    body.v[:, 0] = 1.0
    body.v[V[:, 1] > 1.5, 2] = 0.5
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(V.shape)
    direction = rng.standard_normal(V.shape)
    return body, V, T, w, direction


def timed(fn, min_of):
    fn()  # warm up (Warp's kernel compilation, kinema's first allocations)
    wall, cpu = [], []
    for _ in range(min_of):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return out, min(wall), min(cpu)


def warp_peer(opts):
    import warp as wp
    wp.config.quiet = True
    wp.init()
    body, V, T, w, direction = problem(opts.n)
    v0 = body.v.copy()
    mass = np.asarray(body.mass, dtype=np.float64)
    Dm = np.stack([V[T[:, k]] - V[T[:, 0]] for k in (1, 2, 3)], axis=2)  # columns X_k - X_0
    Dm_inv = np.linalg.inv(Dm)
    vol = np.abs(np.linalg.det(Dm)) / 6
    mu = E / (2 * (1 + NU))
    lam = E * NU / ((1 + NU) * (1 - 2 * NU))
    lam_p = lam + mu
    alpha = 1 + mu / lam_p
    steps, dev = opts.steps, "cpu"

    @wp.kernel
    def tet_forces(x: wp.array(dtype=wp.vec3d), tets: wp.array(dtype=wp.int32, ndim=2),
                   Dm_inv: wp.array(dtype=wp.mat33d), vol: wp.array(dtype=wp.float64),
                   mu: wp.float64, lam_p: wp.float64, alpha: wp.float64, f: wp.array(dtype=wp.vec3d)):
        e = wp.tid()
        i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        x0 = x[i0]
        Ds = wp.matrix_from_cols(x[i1] - x0, x[i2] - x0, x[i3] - x0)
        F = Ds * Dm_inv[e]
        c0 = wp.vec3d(F[0, 0], F[1, 0], F[2, 0])
        c1 = wp.vec3d(F[0, 1], F[1, 1], F[2, 1])
        c2 = wp.vec3d(F[0, 2], F[1, 2], F[2, 2])
        cof = wp.matrix_from_cols(wp.cross(c1, c2), wp.cross(c2, c0), wp.cross(c0, c1))
        J = wp.determinant(F)
        P = mu * F + lam_p * (J - alpha) * cof
        H = -vol[e] * P * wp.transpose(Dm_inv[e])
        h1 = wp.vec3d(H[0, 0], H[1, 0], H[2, 0])
        h2 = wp.vec3d(H[0, 1], H[1, 1], H[2, 1])
        h3 = wp.vec3d(H[0, 2], H[1, 2], H[2, 2])
        wp.atomic_add(f, i1, h1)
        wp.atomic_add(f, i2, h2)
        wp.atomic_add(f, i3, h3)
        wp.atomic_sub(f, i0, h1 + h2 + h3)

    @wp.kernel
    def integrate(x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.vec3d),
                  m: wp.array(dtype=wp.float64), h: wp.float64, g: wp.vec3d,
                  x_out: wp.array(dtype=wp.vec3d), v_out: wp.array(dtype=wp.vec3d)):
        i = wp.tid()
        vn = v[i] + h * (f[i] / m[i] + g)
        v_out[i] = vn
        x_out[i] = x[i] + h * vn

    tets = wp.array(T.astype(np.int32), dtype=wp.int32, device=dev)
    dmi = wp.array(Dm_inv, dtype=wp.mat33d, device=dev)
    volw = wp.array(vol, dtype=wp.float64, device=dev)
    mw = wp.array(mass, dtype=wp.float64, device=dev)
    h, g = wp.float64(DT), wp.vec3d(0.0, G, 0.0)
    consts = (wp.float64(mu), wp.float64(lam_p), wp.float64(alpha))

    def step(x, v, f, x_out, v_out):
        wp.launch(tet_forces, dim=len(T), inputs=[x, tets, dmi, volw, *consts], outputs=[f], device=dev)
        wp.launch(integrate, dim=len(V), inputs=[x, v, f, mw, h, g], outputs=[x_out, v_out], device=dev)

    run = TapeRun(wp, wp.vec3d, V, w, steps, step, dev)
    grad, wall, cpu = timed(lambda: run.gradient(v0), opts.min_of)
    print(json.dumps({"seconds": wall, "cpu_seconds": cpu, "loss": run.forward(v0),
                      "directional": float(np.sum(grad * direction)), "threads": 1}), flush=True)


def kinema_side(opts):
    import kinema as km
    body, V, T, w, direction = problem(opts.n)
    start = body.state()
    steps = opts.steps

    def loss_of(v0):
        body.set_state(start)
        body.v = v0
        for _ in range(steps):
            body.step(DT, integrator="symplectic")
        return float(np.sum(w * body.x))

    v0 = start["v"].reshape(V.shape).copy()
    value = loss_of(v0)
    fd_h = 1e-5
    fd = (loss_of(v0 + fd_h * direction) - loss_of(v0 - fd_h * direction)) / (2 * fd_h)

    def gradient():
        body.set_state(start)
        run = km.diff.rollout(body, steps, DT, wrt=("v",), integrator="symplectic")
        return run.backward({"x": w})["v"]

    grad, wall, cpu = timed(gradient, opts.min_of)
    # Per-step split (CPU time, best of 10): one forward step, one adjoint step asking for no
    # parameter (as the gradient above does) and one asking for all four.
    options = {"integrator": "symplectic"}
    body.set_state(start)
    body._diff_step(DT, None, options)
    after, grads = body.state(), {"x": w, "v": np.zeros_like(w)}

    def forward_step():
        body.set_state(start)
        body._diff_step(DT, None, options)

    split = {"forward": timed(forward_step, 10)[2]}
    for label, wanted in (("adjoint", ()), ("adjoint, all parameters", None)):
        body._diff_want(wanted)
        split[label] = timed(lambda: body._diff_step_adjoint(DT, start, after, None, grads, options), 10)[2]
    body._diff_want(None)
    print("kinema per step (CPU): " + ", ".join(f"{k} {v * 1e3:.2f} ms" for k, v in split.items()), flush=True)
    return {"seconds": wall, "cpu_seconds": cpu, "loss": value, "fd": fd,
            "directional": float(np.sum(grad * direction)), "threads": harness.default_threads()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--n", type=int, default=20, help="vertices per edge of the cube")
    p.add_argument("--min-of", type=int, default=3)
    p.add_argument("--warp", action="store_true", help=argparse.SUPPRESS)
    opts = p.parse_args(argv)
    if opts.warp:
        return warp_peer(opts)
    results = {"kinema": kinema_side(opts)}
    fd = results["kinema"]["fd"]
    cmd = [sys.executable, __file__, "--warp", "--steps", str(opts.steps), "--n", str(opts.n),
           "--min-of", str(opts.min_of)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode == 0:
        results["warp"] = json.loads(done.stdout.strip().splitlines()[-1])
    else:
        print(f"warp: failed ({done.stderr.strip().splitlines()[-1] if done.stderr else done.returncode})")
    print(f"threads {harness.default_threads()}, commit {harness.git_commit()}, {opts.steps} symplectic steps "
          f"of dt = {DT}, cube of {opts.n}^3 vertices; finite difference (kinema forward, h = 1e-5) {fd:.12e}; "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    base = results["kinema"]
    for name, r in results.items():
        err = abs(r["directional"] - fd) / abs(fd)
        r["fd_relative_error"] = err
        print(f"{name:>7}: {r['seconds'] * 1e3:9.1f} ms per gradient ({r['threads']} thread(s)), "
              f"{r['seconds'] / base['seconds']:5.2f} x kinema; CPU {r['cpu_seconds'] * 1e3:9.1f} ms "
              f"({r['cpu_seconds'] / base['cpu_seconds']:5.2f} x); loss {r['loss']:.12e}; directional "
              f"{r['directional']:.12e}, vs finite difference {err:.1e}", flush=True)
    if "warp" in results:
        r = results["warp"]
        print(f"summary: fem cube gradient of {opts.steps} symplectic steps: warp / kinema = "
              f"{r['seconds'] / base['seconds']:.2f}x wall, {r['cpu_seconds'] / base['cpu_seconds']:.2f}x CPU "
              f"(target >= 3x); FD agreement kinema {base['fd_relative_error']:.1e}, warp "
              f"{r['fd_relative_error']:.1e}", flush=True)
    return results


if __name__ == "__main__":
    main()
