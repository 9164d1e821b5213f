"""A mass-spring walker learns to move right by gradient descent through its simulation
(km.diff; the mass_spring task of DiffTaichi: Hu et al., "DiffTaichi: differentiable
programming for physical simulation", ICLR 2020).

    .venv/bin/python examples/diff_walker.py --out demo_output/walker [--iterations 40] [--steps 300]

The robot is a 2D lattice of 5 x 3 vertices (structural and shear springs) standing on the
ground y = 0. Its structural springs are muscles: their rest lengths follow
L_s(t) = L0_s (1 + 0.15 a_s(t)), a(t) = tanh(W s(t) + b), where s(t) holds sinusoids of one
clock (2 Hz, four phases): the controller (W, b) is learned. The ground pushes with a penalty
force k_g max(0, -y) and damps the motion of touching vertices (viscous friction), forces added
as km.diff controls. Each step is a one-step rollout (the rest lengths change every step); the
rollouts chain, and the ground force's dependence on the state closes the chain rule:
dL/dx_t += (du_t/dx_t)^T dL/du_t. Loss: minus the centre of mass's x after the run.
Writes walker_loss.png (loss against iteration) and walker_paths.png (the centre of mass's
path before and after training).
"""

import argparse
import time
from pathlib import Path

import numpy as np

import kinema as km

GROUND_K, GROUND_C, FRICTION = 2e3, 5.0, 20.0
AMPLITUDE, CLOCK_HZ, PHASES = 0.15, 2.0, 4


def robot():
    x, springs, kinds = km.massspring.cloth(5, 3, (0.4, 0.2), dim=2, return_kinds=True)
    keep = kinds < 2  # structural and shear; no bending springs
    springs, kinds = springs[keep], kinds[keep]
    x[:, 1] += 0.01
    sys = km.massspring.System(x, springs, stiffness=400.0, mass=0.02, damping=0.1,
                               gravity=(0.0, -9.81))
    return sys, np.flatnonzero(kinds == 0)


def ground(x, v):
    """Penalty and friction forces of the ground y = 0 and their (diagonal) derivatives."""
    touch = (x[:, 1] < 0).astype(float)
    u = np.zeros_like(x)
    u[:, 1] = touch * (-GROUND_K * x[:, 1] - GROUND_C * v[:, 1])
    u[:, 0] = -touch * FRICTION * v[:, 0]
    du_dx = np.zeros_like(x)
    du_dx[:, 1] = -GROUND_K * touch
    du_dv = np.zeros_like(x)
    du_dv[:, 1] = -GROUND_C * touch
    du_dv[:, 0] = -FRICTION * touch
    return u, du_dx, du_dv


def clock(t):
    return np.sin(2 * np.pi * CLOCK_HZ * t + 2 * np.pi * np.arange(PHASES) / PHASES)


def simulate(W, b, steps, dt, *, grad=False):
    """Runs the walker; returns the loss, the centre of mass's path and, with grad, dL/dW, dL/db."""
    sys, muscles = robot()
    rest0 = sys._diff_get("rest_length")
    start = sys.state()
    runs, path = [], [sys.x.mean(axis=0)]
    for k in range(steps):
        s = clock(k * dt)
        a = np.tanh(W @ s + b)
        rest = rest0.copy()
        rest[muscles] *= 1 + AMPLITUDE * a
        sys._diff_set("rest_length", rest)
        u, du_dx, du_dv = ground(sys.x, sys.v)
        runs.append((km.diff.rollout(sys, 1, dt, wrt=("x", "v", "rest_length", "controls"), controls=u[None],
                                     integrator="symplectic") if grad else None, rest, s, a, du_dx, du_dv))
        if not grad:
            sys._diff_step(dt, u, {"integrator": "symplectic"})
        path.append(sys.x.mean(axis=0))
    loss = -float(sys.x[:, 0].mean())
    if not grad:
        return loss, np.array(path)
    n = len(sys.x)
    g = {"x": np.zeros_like(sys.x), "v": np.zeros_like(sys.v)}
    g["x"][:, 0] = -1.0 / n
    gW, gb = np.zeros_like(W), np.zeros_like(b)
    for run, rest, s, a, du_dx, du_dv in reversed(runs):
        sys._diff_set("rest_length", rest)  # the adjoint of step k sees step k's rest lengths
        out = run.backward(g)
        gu = out["controls"][0]
        # rest[muscles] = L0 (1 + A a): dL/da = dL/drest * L0 A, then through tanh.
        ga = out["rest_length"][muscles] * rest0[muscles] * AMPLITUDE * (1 - a**2)
        gW += np.outer(ga, s)
        gb += ga
        g = {"x": out["x"], "v": out["v"]}
        if gu is not None:
            g["x"] = g["x"] + du_dx * gu
            g["v"] = g["v"] + du_dv * gu
    sys.set_state(start)
    return loss, np.array(path), gW, gb


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="demo_output/walker")
    p.add_argument("--iterations", type=int, default=40)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--dt", type=float, default=1.5e-3)
    p.add_argument("--lr", type=float, default=0.1)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _, muscles = robot()
    rng = np.random.default_rng(0)
    W = 0.1 * rng.standard_normal((len(muscles), PHASES))
    b = np.zeros(len(muscles))
    losses, first_path = [], None
    m1, m2 = [np.zeros_like(W), np.zeros_like(b)], [np.zeros_like(W), np.zeros_like(b)]
    t0 = time.perf_counter()
    for it in range(args.iterations):
        loss, path, gW, gb = simulate(W, b, args.steps, args.dt, grad=True)
        if first_path is None:
            first_path = path
        losses.append(loss)
        norm = np.sqrt(np.sum(gW**2) + np.sum(gb**2))
        # Adam (Kingma and Ba 2015): steps of about lr whatever the gradient's scale, lr
        # decaying so that the walk settles (the contacts make the loss rough at small scales).
        lr = args.lr / (1 + it / 10)
        for k, (theta, g) in enumerate(((W, gW), (b, gb))):
            m1[k] = 0.9 * m1[k] + 0.1 * g
            m2[k] = 0.999 * m2[k] + 0.001 * g**2
            theta -= lr * (m1[k] / (1 - 0.9 ** (it + 1))) / (
                np.sqrt(m2[k] / (1 - 0.999 ** (it + 1))) + 1e-12)
        print(f"iteration {it:3d}: loss {loss:+.4f} m (moved {path[-1, 0] - path[0, 0]:+.3f} m), "
              f"|grad| {norm:.2e}, {time.perf_counter() - t0:.1f} s", flush=True)
    final, path = simulate(W, b, args.steps, args.dt)
    losses.append(final)
    print(f"final loss {final:+.4f} (first {losses[0]:+.4f}); moved {path[-1, 0] - path[0, 0]:+.3f} m right")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(len(losses)), losses, "o-", ms=3)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss = -x of the centre of mass [m]")
    ax.set_title("mass-spring walker (km.diff)")
    fig.tight_layout()
    fig.savefig(out / "walker_loss.png", dpi=120)
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(first_path[:, 0], first_path[:, 1], label="before training")
    ax.plot(path[:, 0], path[:, 1], label="after training")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend()
    ax.set_title("centre of mass")
    fig.tight_layout()
    fig.savefig(out / "walker_paths.png", dpi=120)
    plt.close("all")
    return losses


if __name__ == "__main__":
    main()
