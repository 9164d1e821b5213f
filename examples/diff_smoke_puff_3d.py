"""A 3D smoke puff steered to a target point by per-step forces learned through the whole run,
on km.grid and km.diff.

    .venv/bin/python examples/diff_smoke_puff_3d.py --out demo_output/diff_puff [--iterations 40]

A closed box of n^3 cells holds a Gaussian puff of smoke in still air, near one corner. Every
step k adds a control acceleration field a_k (one 3-vector per cell), so the controls are
steps x n^3 x 3 numbers. The loss is the smoke's mean squared distance from the target point p
after the run, L = sum(rho |x - p|^2) / sum(rho) (the squared distance of its centre of mass
plus its spread, so the puff must arrive as a puff, not be smeared until its centroid hits p),
plus a small penalty lambda/2 sum |a|^2 h^3 dt: dL/d(rho_T) = (|x - p|^2 - L) / sum(rho), and
one km.diff rollout (checkpointed, K = 2 sqrt(steps)) turns it into dL/da for every step; Adam
updates them.

Writes loss.png (loss against iteration) and puff.png (the smoke's column density seen along z
and along x, before and after learning, with the target marked); prints the loss per iteration.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import Adam, plot_loss, pyplot  # noqa: E402


def make_fluid(n, start):
    sim = km.grid.Fluid((n, n, n), 1.0 / n, advection="maccormack", rk_order=2, density=True, tol=1e-8)
    c = sim.cell_centers()
    sim.density = np.exp(-np.sum((c - start) ** 2, -1) / (2 * 0.08 ** 2))
    return sim, c


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/diff_puff"))
    parser.add_argument("--cells", type=int, default=24, help="cells per side")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--dt", type=float, default=0.04, help="step [s]")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--learning-rate", type=float, default=0.5, help="Adam step on the accelerations [m/s^2]")
    parser.add_argument("--penalty", type=float, default=1e-3)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    n, h = args.cells, 1.0 / args.cells
    start, goal = np.array([0.3, 0.3, 0.3]), np.array([0.7, 0.65, 0.6])
    sim, x = make_fluid(n, start)
    s0 = sim.state()
    controls = np.zeros((args.steps, n, n, n, 3))
    adam = Adam(args.learning_rate)
    losses, centres = [], []
    K = int(2 * np.sqrt(args.steps)) + 1
    for it in range(args.iterations):
        t0 = time.perf_counter()
        sim.set_state(s0)
        run = km.diff.rollout(sim, args.steps, args.dt, wrt=("controls",), controls=controls, checkpoints=K)
        rho = run.outputs["density"]
        mass = rho.sum()
        c = np.tensordot(rho, x, axes=3) / mass
        r2 = np.sum((x - goal) ** 2, -1)
        loss = float(np.sum(rho * r2) / mass)
        penalty = 0.5 * args.penalty * float(np.sum(controls ** 2)) * h ** 3 * args.dt
        grad_rho = (r2 - loss) / mass
        g = run.backward({"density": grad_rho})["controls"] + args.penalty * controls * h ** 3 * args.dt
        adam.step([controls], [g])
        losses.append(loss + penalty)
        centres.append(c)
        print(f"iteration {it:3d}  rms distance {np.sqrt(loss):.4f} m  centre {np.round(c, 3)}  "
              f"{time.perf_counter() - t0:.2f} s", flush=True)
    sim.set_state(s0)
    before = sim.density.copy()
    for k in range(args.steps):
        sim._diff_step(args.dt, controls[k], {})
    after = sim.density.copy()
    c_end = np.tensordot(after, x, axes=3) / after.sum()
    print(f"centre to the target: {np.linalg.norm(centres[0] - goal):.4f} m without control -> "
          f"{np.linalg.norm(c_end - goal):.4f} m after {args.iterations} iterations")

    plot_loss(args.out / "loss.png", losses, "mean |x - target|^2 + penalty [m^2]",
              f"3D smoke puff to a point: {n}^3 cells, {args.steps} steps")
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(11, 3))
    panels = [(before, 2, "start, along z"), (after, 2, "learned, along z"), (before, 0, "start, along x"),
              (after, 0, "learned, along x")]
    for a, (field, axis, title) in zip(axes, panels):
        a.imshow(field.sum(axis=axis).T, origin="lower", cmap="magma", extent=(0, 1, 0, 1))
        u, w = (0, 1) if axis == 2 else (1, 2)
        a.plot(goal[u], goal[w], "c+", ms=14, mew=2)
        a.set_title(title)
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(args.out / "puff.png", dpi=120)
    plt.close("all")
    return losses, float(np.linalg.norm(centres[0] - goal)), float(np.linalg.norm(c_end - goal))


if __name__ == "__main__":
    main()
