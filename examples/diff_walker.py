"""A mass-spring walker learns to move right by gradient descent through its simulation
(km.diff; the mass_spring task of DiffTaichi: Hu et al., "DiffTaichi: differentiable
programming for physical simulation", ICLR 2020).

    .venv/bin/python examples/diff_walker.py --out demo_output/walker [--iterations 40] [--steps 300]

The robot is a 2D lattice of 5 x 3 vertices (structural and shear springs) standing on the
ground y = 0. Its structural springs are muscles: their rest lengths follow
L_s(t) = L0_s (1 + 0.15 a_s(t)). The controller is DiffTaichi's: a network with one hidden layer
fed with the state, h = tanh(W1 z(t) + b1), a = tanh(W2 h + b2), whose input z(t) holds sinusoids
of one clock (2 Hz, four phases) and, scaled by 0.05 as in DiffTaichi, every vertex's position
relative to the centre of mass and its velocity (DiffTaichi's input also has the offset to a goal;
here the loss is the distance walked, so there is none). (W1, b1, W2, b2) are learned.
The ground pushes with a penalty force k_g max(0, -y) and damps the motion of touching vertices
(viscous friction), forces added as km.diff controls. Each step is a one-step rollout (the rest
lengths change every step); the rollouts chain, and the gradient flows through both feedbacks of
the state: the ground force's, dL/dx_t += (du_t/dx_t)^T dL/du_t, and the controller's,
dL/d(x_t, v_t) += (dz_t/d(x_t, v_t))^T W1^T ... dL/da_t. Loss: minus the centre of mass's x after
the run. Writes walker_loss.png (loss against iteration) and walker_paths.png (the centre of
mass's path before and after training).
"""

import argparse
import time
from pathlib import Path

import numpy as np

import kinema as km

GROUND_K, GROUND_C, FRICTION = 2e3, 5.0, 20.0
AMPLITUDE, CLOCK_HZ, PHASES, HIDDEN = 0.15, 2.0, 4, 32


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


STATE_SCALE = 0.05  # DiffTaichi's weight on the state inputs ("there are too many of them")


def controller_input(t, x, v):
    """z(t): the clock's sinusoids, then 0.05 (x_i - centre) and 0.05 v_i of every vertex."""
    return np.concatenate([clock(t), STATE_SCALE * (x - x.mean(axis=0)).ravel(), STATE_SCALE * v.ravel()])


def controller(net, z):
    """a = tanh(W2 tanh(W1 z + b1) + b2); returns a and the hidden layer h."""
    W1, b1, W2, b2 = net
    h = np.tanh(W1 @ z + b1)
    return np.tanh(W2 @ h + b2), h


def controller_backward(net, z, h, a, ga, grads):
    """Adds dL/d(W1, b1, W2, b2) to grads from dL/da; returns dL/dz."""
    W1, _, W2, _ = net
    g2 = ga * (1 - a**2)
    grads[2] += np.outer(g2, h)
    grads[3] += g2
    g1 = (W2.T @ g2) * (1 - h**2)
    grads[0] += np.outer(g1, z)
    grads[1] += g1
    return W1.T @ g1


def simulate(net, steps, dt, *, grad=False):
    """Runs the walker; returns the loss, the centre of mass's path and, with grad, the list of
    dL/d(W1, b1, W2, b2)."""
    sys, muscles = robot()
    rest0 = sys._diff_get("rest_length")
    start = sys.state()
    n, d = sys.x.shape
    runs, path = [], [sys.x.mean(axis=0)]
    for k in range(steps):
        z = controller_input(k * dt, sys.x, sys.v)
        a, h = controller(net, z)
        rest = rest0.copy()
        rest[muscles] *= 1 + AMPLITUDE * a
        sys._diff_set("rest_length", rest)
        u, du_dx, du_dv = ground(sys.x, sys.v)
        runs.append((km.diff.rollout(sys, 1, dt, wrt=("x", "v", "rest_length", "controls"), controls=u[None],
                                     integrator="symplectic") if grad else None, rest, z, h, a, du_dx, du_dv))
        if not grad:
            sys._diff_step(dt, u, {"integrator": "symplectic"})
        path.append(sys.x.mean(axis=0))
    loss = -float(sys.x[:, 0].mean())
    if not grad:
        return loss, np.array(path)
    g = {"x": np.zeros_like(sys.x), "v": np.zeros_like(sys.v)}
    g["x"][:, 0] = -1.0 / n
    grads = [np.zeros_like(p) for p in net]
    for run, rest, z, h, a, du_dx, du_dv in reversed(runs):
        sys._diff_set("rest_length", rest)  # the adjoint of step k sees step k's rest lengths
        out = run.backward(g)
        gu = out["controls"][0]
        # rest[muscles] = L0 (1 + A a): dL/da = dL/drest * L0 A, then through the network.
        ga = out["rest_length"][muscles] * rest0[muscles] * AMPLITUDE
        gz = controller_backward(net, z, h, a, ga, grads)
        # z's state part: 0.05 (x_i - mean_j x_j) and 0.05 v_i.
        gzx = gz[PHASES:PHASES + n * d].reshape(n, d)
        gzv = gz[PHASES + n * d:].reshape(n, d)
        g = {"x": out["x"] + STATE_SCALE * (gzx - gzx.mean(axis=0)), "v": out["v"] + STATE_SCALE * gzv}
        if gu is not None:
            g["x"] = g["x"] + du_dx * gu
            g["v"] = g["v"] + du_dv * gu
    sys.set_state(start)
    return loss, np.array(path), grads


def initial_controller(muscles, n, hidden=HIDDEN, seed=0):
    """(W1, b1, W2, b2), small random weights (DiffTaichi's initialisation scale)."""
    rng = np.random.default_rng(seed)
    inputs = PHASES + 4 * n
    return [rng.standard_normal((hidden, inputs)) * np.sqrt(2 / (hidden + inputs)) * 2, np.zeros(hidden),
            rng.standard_normal((len(muscles), hidden)) * np.sqrt(2 / (hidden + len(muscles))) * 2,
            np.zeros(len(muscles))]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="demo_output/walker")
    p.add_argument("--iterations", type=int, default=40)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--dt", type=float, default=1.5e-3)
    p.add_argument("--lr", type=float, default=0.03)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sys, muscles = robot()
    net = initial_controller(muscles, len(sys.x))
    losses, first_path = [], None
    m1, m2 = [np.zeros_like(p) for p in net], [np.zeros_like(p) for p in net]
    t0 = time.perf_counter()
    for it in range(args.iterations):
        loss, path, grads = simulate(net, args.steps, args.dt, grad=True)
        if first_path is None:
            first_path = path
        losses.append(loss)
        norm = np.sqrt(sum(np.sum(g**2) for g in grads))
        # Adam (Kingma and Ba 2015): steps of about lr whatever the gradient's scale, lr
        # decaying so that the walk settles (the contacts make the loss rough at small scales).
        lr = args.lr / (1 + it / 4)
        for k, (theta, g) in enumerate(zip(net, grads)):
            m1[k] = 0.9 * m1[k] + 0.1 * g
            m2[k] = 0.999 * m2[k] + 0.001 * g**2
            theta -= lr * (m1[k] / (1 - 0.9 ** (it + 1))) / (
                np.sqrt(m2[k] / (1 - 0.999 ** (it + 1))) + 1e-12)
        print(f"iteration {it:3d}: loss {loss:+.4f} m (moved {path[-1, 0] - path[0, 0]:+.3f} m), "
              f"|grad| {norm:.2e}, {time.perf_counter() - t0:.1f} s", flush=True)
    final, path = simulate(net, args.steps, args.dt)
    losses.append(final)
    print(f"final loss {final:+.4f} (first {losses[0]:+.4f}); moved {path[-1, 0] - path[0, 0]:+.3f} m right")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(len(losses)), losses, "o-", ms=3)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss = -x of the centre of mass [m]")
    ax.set_title("mass-spring walker, state-fed controller (km.diff)")
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
