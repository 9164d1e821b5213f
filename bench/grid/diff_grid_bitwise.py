"""The km.grid gradients of many configurations, written to an .npz, or compared bit for bit with
one written before: the check that a speed change of the adjoint left every gradient as it was
(run it once with a baseline build on PYTHONPATH, once with this one; also across
KINEMA_SIMD=baseline and thread counts, whose bits must agree too).

    PYTHONPATH=<main's site-packages> .venv/bin/python bench/grid/diff_grid_bitwise.py --write /tmp/main.npz
    .venv/bin/python bench/grid/diff_grid_bitwise.py --compare /tmp/main.npz [--threads 2]
    KINEMA_SIMD=baseline .venv/bin/python bench/grid/diff_grid_bitwise.py --compare /tmp/main.npz --threads 2

Cases: 2D and 3D; semi-Lagrangian, MacCormack, BFECC; RK1-3; closed (with a solid block, a
density source and buoyancy), periodic, and open sides; viscosity 0 and > 0; km.diff's backward
with every state stored (C++ record) and checkpointed (step by step, kept advection scratch);
gradients of the initial state, the controls and the viscosity. Prints one SUMMARY line.
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

import kinema as km


def run(dim, advection, rk, setup, nu, checkpoints):
    n = 20 if dim == 2 else 10
    shape = (n,) * dim
    h = 1.0 / n
    kw = dict(advection=advection, rk_order=rk, tol=1e-10, density=True, viscosity=nu, buoyancy=(0.5, 0.0))
    if setup == "periodic":
        kw["boundary"] = "periodic"
    if setup == "open":
        kw["open"] = ("y+",)
    sim = km.grid.Fluid(shape, h, **kw)
    rng = np.random.default_rng(7)
    c = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) * h for _ in range(dim)], indexing="ij"), -1)
    sim.density = np.exp(-np.sum((c - 0.4) ** 2, -1) / 0.02)
    for name in ("u", "v", "w")[:dim]:
        arr = getattr(sim, name)
        setattr(sim, name, 0.5 * rng.normal(size=arr.shape))
    if setup == "closed":
        solid = np.zeros(shape, bool)
        solid[(slice(n // 2, n // 2 + 2),) * dim] = True
        sim.solid = solid
        region = np.zeros(shape, bool)
        region[(slice(1, 3),) * dim] = True
        sim.add_source(region, density=1.0)
    steps = 4
    dt = 0.4 * h
    controls = rng.normal(size=(steps,) + shape + (dim,))
    weights = {k: rng.normal(size=np.shape(v)) for k, v in sim.state().items() if k in sim._diff_state_names}
    run = km.diff.rollout(sim, steps, dt, wrt=("controls", "viscosity") + sim._diff_state_names,
                          controls=controls, checkpoints=checkpoints)
    grads = run.backward(weights)
    return {k: np.asarray(v, float) for k, v in grads.items()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", help="write the gradients to this .npz")
    ap.add_argument("--compare", help="compare the gradients bit for bit with this .npz")
    ap.add_argument("--threads", type=int, default=1)
    opts = ap.parse_args()
    km.set_num_threads(opts.threads)
    out = {}
    for dim, advection, rk, setup, nu, ck in itertools.product(
            (2, 3), ("semi_lagrangian", "maccormack", "bfecc"), (1, 2, 3), ("closed", "periodic", "open"),
            (0.0, 1e-3), (None, 2)):
        if rk != 2 and (setup != "closed" or nu > 0):
            continue  # RK1 and RK3 in the closed box without viscosity only
        tag = f"{dim}D-{advection}-rk{rk}-{setup}-nu{nu:g}-{'ck' if ck else 'stored'}"
        for name, g in run(dim, advection, rk, setup, nu, ck).items():
            out[f"{tag}-{name}"] = g
    if opts.write:
        np.savez(opts.write, **out)
        print(f"SUMMARY: {len(out)} gradient arrays written to {opts.write}")
    if opts.compare:
        ref = np.load(opts.compare)
        differ = [k for k in out if k not in ref or ref[k].shape != out[k].shape
                  or not np.array_equal(ref[k].view(np.uint64), out[k].view(np.uint64))]
        missing = [k for k in ref.files if k not in out]
        for k in differ[:10]:
            print("differs:", k)
        print(f"SUMMARY: {len(out)} gradient arrays compared with {opts.compare}, {len(differ)} differ, "
              f"{len(missing)} missing (threads {opts.threads})")
        raise SystemExit(1 if differ or missing else 0)


if __name__ == "__main__":
    main()
