"""Throw a cloth at a target: its initial velocity is optimised by gradient descent through an
implicit mass-spring simulation (km.diff; the cloth_throw task of NVIDIA Warp's examples).

    .venv/bin/python examples/diff_cloth_throw.py --out demo_output/cloth_throw [--iterations 30] [--n 16]

A square cloth of n x n vertices (0.5 m, structural, shear and bending springs) starts
horizontal 1 m above the origin and flies for `steps` implicit steps under gravity. The loss is
|c(T) - target|^2, c the cloth's centre of mass at the end; its gradient with respect to the
initial velocity of every vertex comes from one km.diff rollout (checkpointed, K = 2 sqrt(T)),
and gradient descent updates that velocity field. Writes cloth_throw_loss.png (loss against
iteration) and cloth_throw_paths.png (the centre of mass's flight at a few iterations).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import plot_loss, pyplot  # noqa: E402

TARGET = np.array([1.0, 1.2, 0.5])


def make_cloth(n):
    x, springs = km.massspring.cloth(n, n, 0.5, plane="xz", origin=(-0.25, 1.0, -0.25))
    return km.massspring.System(x, springs, stiffness=2e3, mass=0.2 / n**2, damping=0.01,
                                gravity=(0.0, -9.81, 0.0))


def flight(sys, v0, steps, dt):
    """The centre of mass's path for the initial velocity v0 (the cloth is reset first)."""
    start = sys.state()
    sys.v = v0
    path = [sys.x.mean(axis=0)]
    for _ in range(steps):
        sys.step(dt)
        path.append(sys.x.mean(axis=0))
    sys.set_state(start)
    return np.array(path)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="demo_output/cloth_throw")
    p.add_argument("--iterations", type=int, default=30)
    p.add_argument("--n", type=int, default=16)
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--dt", type=float, default=1 / 60)
    p.add_argument("--lr", type=float, default=0.6)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sys = make_cloth(args.n)
    start = sys.state()
    n = len(sys.x)
    v0 = np.zeros_like(sys.x)
    K = max(2, int(2 * np.sqrt(args.steps)))
    losses, paths = [], []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        sys.set_state(start)
        sys.v = v0
        run = km.diff.rollout(sys, args.steps, args.dt, wrt=("v",), checkpoints=K)
        c = run.outputs["x"].mean(axis=0)
        loss = float(np.sum((c - TARGET) ** 2))
        g = run.backward({"x": np.broadcast_to(2 * (c - TARGET) / n, (n, 3))})["v"]
        losses.append(loss)
        if it in (0, args.iterations // 3, args.iterations - 1):
            paths.append((it, flight(sys, v0, args.steps, args.dt)))
        # Gradient descent on the velocity field. For a rigid throw c(T) = c(0) + T v + gravity's
        # part, so the loss's curvature along a uniform change of v is 2 T^2 / n per vertex:
        # the step is scaled by its inverse, and lr = 1 would hit the target of a rigid throw in
        # one step.
        flight_time = args.steps * args.dt
        v0 = v0 - args.lr * n * g / (2 * flight_time**2)
        print(f"iteration {it:3d}: loss {loss:.3e} m^2, |c(T) - target| {np.sqrt(loss):.3f} m, "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    sys.set_state(start)
    sys.v = v0
    for _ in range(args.steps):
        sys.step(args.dt)
    final = float(np.sum((sys.x.mean(axis=0) - TARGET) ** 2))
    losses.append(final)
    print(f"final |c(T) - target| {np.sqrt(final):.4f} m (first {np.sqrt(losses[0]):.3f} m)")
    plot_loss(out / "cloth_throw_loss.png", losses, "loss |c(T) - target|^2 [m^2]",
              "cloth throw (km.diff, implicit mass-spring)")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 4))
    for it, path in paths:
        ax.plot(path[:, 0], path[:, 1], label=f"iteration {it}")
    ax.plot(TARGET[0], TARGET[1], "k*", ms=12, label="target")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend()
    ax.set_title("centre of mass (side view)")
    fig.tight_layout()
    fig.savefig(out / "cloth_throw_paths.png", dpi=120)
    plt.close("all")
    return losses


if __name__ == "__main__":
    main()
