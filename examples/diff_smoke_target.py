"""2D smoke steered into a target image by per-step forces learned through the whole run: the
smoke control problem of DiffTaichi (Hu et al. 2020, "smoke_taichi") and PhiFlow (Holl, Koltun
and Thuerey 2020), on km.grid and km.diff.

    .venv/bin/python examples/diff_smoke_target.py --out demo_output/diff_smoke [--iterations 150]

A closed box of n x n cells holds a disc of smoke (density 1) in still air. Every step k of the
run adds a control acceleration field a_k (one 2-vector per cell, averaged to the MAC faces,
then projected with the rest of the step), so the controls are steps x n x n x 2 numbers. The
loss is L = 1/2 sum (density_T - target)^2 h^2 after the run, the target an image of the same
total mass (a ring, or a cross with --target cross). One km.diff rollout and its backward pass
give dL/da for every step; Adam (Kingma and Ba 2015) updates the controls, with a small
penalty lambda/2 sum |a|^2 h^2 dt that keeps them from growing where they do nothing.

Writes loss.png (loss against iteration), frames.png (the target, then the run with the first
and with the last controls at a few times) and smoke_target.npz (final density, target, losses);
prints the loss of each iteration. The default settings take a few minutes on 2 cores.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import Adam, plot_loss, pyplot  # noqa: E402


def target_image(n, kind, mass):
    """A ring (or a cross) on n x n cells scaled to the given total density."""
    x = (np.arange(n) + 0.5) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    r = np.hypot(X - 0.5, Y - 0.55)
    if kind == "ring":
        img = np.exp(-((r - 0.22) / 0.05) ** 2)
    elif kind == "cross":
        bar = lambda s, t: np.exp(-(s / 0.06) ** 2) * (np.abs(t) < 0.3)
        img = np.maximum(bar(X - 0.5, Y - 0.55), bar(Y - 0.55, X - 0.5)).astype(float)
    else:
        raise ValueError(f"target: expected 'ring' or 'cross', got {kind!r}")
    return img * mass / img.sum()


def make_fluid(n, advection):
    sim = km.grid.Fluid((n, n), 1.0 / n, advection=advection, rk_order=2, density=True, tol=1e-8)
    c = sim.cell_centers()
    sim.density = 1.0 / (1 + np.exp((np.hypot(c[..., 0] - 0.5, c[..., 1] - 0.3) - 0.15) * 4 * n))  # a soft disc
    return sim


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/diff_smoke"))
    parser.add_argument("--cells", type=int, default=64, help="cells per side")
    parser.add_argument("--steps", type=int, default=40, help="steps of the run")
    parser.add_argument("--dt", type=float, default=0.025, help="step [s]")
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--learning-rate", type=float, default=0.3, help="Adam step on the accelerations [m/s^2]")
    parser.add_argument("--penalty", type=float, default=1e-4, help="lambda of the control penalty")
    parser.add_argument("--target", default="ring", choices=("ring", "cross"))
    parser.add_argument("--advection", default="maccormack", choices=km.grid.SCHEMES)
    parser.add_argument("--checkpoints", type=int, default=None, help="K states held (default: all)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    n, h = args.cells, 1.0 / args.cells
    sim = make_fluid(n, args.advection)
    s0 = sim.state()
    target = target_image(n, args.target, sim.density.sum())
    controls = np.zeros((args.steps, n, n, 2))
    adam = Adam(args.learning_rate)
    losses, first = [], None
    for it in range(args.iterations):
        start = time.perf_counter()
        sim.set_state(s0)
        run = km.diff.rollout(sim, args.steps, args.dt, wrt=("controls",), controls=controls,
                              checkpoints=args.checkpoints)
        rho = run.outputs["density"]
        misfit = rho - target
        loss = 0.5 * float(np.sum(misfit ** 2)) * h * h
        effort = 0.5 * args.penalty * float(np.sum(controls ** 2)) * h * h * args.dt
        if first is None:
            first = rho.copy()
        g = run.backward({"density": misfit * h * h})["controls"] + args.penalty * controls * h * h * args.dt
        adam.step([controls], [g])
        losses.append(loss + effort)
        print(f"iteration {it:3d}  loss {loss:.4e}  penalty {effort:.2e}  {time.perf_counter() - start:.2f} s",
              flush=True)
    # the run with the last controls, with a few frames
    shown = sorted({0, args.steps // 3, 2 * args.steps // 3, args.steps})
    frames = {"first": {}, "last": {}}
    for key, c in (("first", np.zeros_like(controls)), ("last", controls)):
        sim.set_state(s0)
        frames[key][0] = sim.density.copy()
        for k in range(args.steps):
            sim._diff_step(args.dt, c[k], {})
            if k + 1 in shown:
                frames[key][k + 1] = sim.density.copy()
    final = frames["last"][args.steps]
    final_loss = 0.5 * float(np.sum((final - target) ** 2)) * h * h
    initial_loss = 0.5 * float(np.sum((first - target) ** 2)) * h * h
    print(f"loss: {initial_loss:.4e} with no control -> {final_loss:.4e} after {args.iterations} iterations "
          f"({final_loss / initial_loss:.3f} of it)")
    np.savez(args.out / "smoke_target.npz", density=final, target=target, losses=np.array(losses))

    plot_loss(args.out / "loss.png", losses, "loss",
              f"smoke to a {args.target}: {n}x{n} cells, {args.steps} steps, {args.advection}", style="-")
    plt = pyplot()
    fig, axes = plt.subplots(2, len(shown) + 1, figsize=(2.2 * (len(shown) + 1), 4.6))
    vmax = max(target.max(), max(f.max() for f in frames["last"].values()))
    for row, key in enumerate(("first", "last")):
        axes[row, 0].imshow(target.T, origin="lower", cmap="magma", vmin=0, vmax=vmax)
        axes[row, 0].set_title("target" if row == 0 else "")
        for j, k in enumerate(shown):
            axes[row, j + 1].imshow(frames[key][k].T, origin="lower", cmap="magma", vmin=0, vmax=vmax)
            axes[row, j + 1].set_title(f"{'no control' if key == 'first' else 'learned'}, t = {k * args.dt:.2f} s",
                                       fontsize=8)
    for a in axes.flat:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(args.out / "frames.png", dpi=120)
    plt.close("all")
    return losses, initial_loss, final_loss


if __name__ == "__main__":
    main()
