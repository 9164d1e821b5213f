"""Throw an SPH droplet at a target: its initial velocity field is optimised by gradient descent
through a WCSPH simulation (km.diff).

    .venv/bin/python examples/diff_sph_droplet.py --out demo_output/sph_droplet [--iterations 12] [--dim 2]

A round droplet of water (2D disc or 3D ball of radius 5 cm, particle spacing 1 cm, WCSPH with
c = 10 m/s, a little viscosity) starts at rest 0.5 m up and flies for `steps` steps under
gravity. The loss is |c(T) - target|^2, c the droplet's centre of mass at the end; its
gradient with respect to the initial velocity of every particle comes from one km.diff rollout
(checkpointed, K = 2 sqrt(T)), and gradient descent updates that velocity field. Each particle's
gradient carries what the pressure and viscous forces pass between the particles during the
flight; the centre of mass itself moves as a point mass (those forces cancel in pairs), so the
loss is quadratic in the mean velocity and descent converges geometrically, at 1 - lr per
iteration in distance. Writes sph_droplet_loss.png (loss against iteration) and sph_droplet_flight.png (the
particles at the end of the flight at the first and the last iteration, with the centre of
mass's path).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import plot_loss, pyplot  # noqa: E402

SPACING = 0.01


def make_droplet(dim):
    """A disc (2D) or ball (3D) of radius 5 cm centred 0.5 m up, as WCSPH particles."""
    r = 0.05
    center = np.array([0.0, 0.5, 0.0][:dim])
    x = km.sph.block(center - r, center + r, SPACING)
    x = x[np.linalg.norm(x - center, axis=1) <= r]
    return km.sph.Fluid(x, SPACING, method="wcsph", speed_of_sound=10.0, viscosity=1e-4,
                        gravity=[0.0, -9.81, 0.0][:dim])


def flight(fluid, start, v0, steps, dt):
    """The centre of mass's path and the final positions from the state `start` with the
    initial velocity v0 (the fluid is left in `start`)."""
    fluid.set_state(start)
    fluid.v = v0
    path = [fluid.x.mean(axis=0)]
    for _ in range(steps):
        fluid.step(dt)
        path.append(fluid.x.mean(axis=0))
    final = fluid.x.copy()
    fluid.set_state(start)
    return np.array(path), final


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="demo_output/sph_droplet")
    p.add_argument("--iterations", type=int, default=12)
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--steps", type=int, default=1300)
    p.add_argument("--dt", type=float, default=3e-4, help="WCSPH step [s] (stable below 0.4 spacing / (c + v))")
    p.add_argument("--lr", type=float, default=0.7)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fluid = make_droplet(args.dim)
    start = fluid.state()
    n, d = fluid.n, fluid.dim
    # The target: where a point thrown from the droplet's centre at (2, 1, 0.5) m/s lands after
    # the flight time T (so the velocity to find is 2.3 m/s, Mach 0.23, whatever T).
    T = args.steps * args.dt
    target = start["x"].mean(axis=0) + T * np.array([2.0, 1.0, 0.5][:d]) + 0.5 * fluid.gravity * T**2
    v0 = np.zeros((n, d))
    K = max(2, int(2 * np.sqrt(args.steps)))
    print(f"{d}D droplet of {n} particles, {args.steps} steps of {args.dt} s, target {np.round(target, 3).tolist()} m")
    losses, flights = [], []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        fluid.set_state(start)
        fluid.v = v0
        run = km.diff.rollout(fluid, args.steps, args.dt, wrt=("v",), checkpoints=K)
        c = run.outputs["x"].mean(axis=0)
        loss = float(np.sum((c - target) ** 2))
        g = run.backward({"x": np.broadcast_to(2 * (c - target) / n, (n, d))})["v"]
        losses.append(loss)
        if it == 0:
            flights.append((it, v0.copy()))
        # Gradient descent on the velocity field. A droplet's centre of mass moves as a point
        # mass (internal forces cancel in pairs), c(T) = c(0) + T mean(v0) + gravity's part, so
        # the loss's curvature along a uniform change of v0 is 2 T^2 / n per particle: the step
        # is scaled by its inverse, and lr = 1 would hit the target in one step.
        v0 = v0 - args.lr * n * g / (2 * T**2)
        print(f"iteration {it:3d}: loss {loss:.3e} m^2, |c(T) - target| {np.sqrt(loss):.4f} m, "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    path, final_x = flight(fluid, start, v0, args.steps, args.dt)
    final = float(np.sum((path[-1] - target) ** 2))
    losses.append(final)
    flights.append((args.iterations, v0))
    print(f"final |c(T) - target| {np.sqrt(final):.5f} m (first {np.sqrt(losses[0]):.3f} m)")

    plot_loss(out / "sph_droplet_loss.png", losses, "loss |c(T) - target|^2 [m^2]",
              f"SPH droplet throw ({d}D WCSPH, km.diff)")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for (it, v), colour in zip(flights, ("tab:gray", "tab:blue")):
        path, x = flight(fluid, start, v, args.steps, args.dt)
        ax.plot(path[:, 0], path[:, 1], "-", color=colour, lw=1)
        ax.scatter(x[:, 0], x[:, 1], s=4, color=colour, label=f"iteration {it}: particles at T = {T:.2f} s")
    ax.scatter(start["x"][:, 0], start["x"][:, 1], s=4, color="k", alpha=0.4, label="start")
    ax.plot(target[0], target[1], "r*", ms=14, label="target")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("droplet flight (side view)")
    fig.tight_layout()
    fig.savefig(out / "sph_droplet_flight.png", dpi=120)
    plt.close("all")
    return losses


if __name__ == "__main__":
    main()
