"""An elastic MPM walker learns to move right: DiffTaichi's diffmpm (Hu et al. 2020, Sec. 5.1)
on km.mpm and km.diff.

    .venv/bin/python examples/diff_mpm_actuation.py --out demo_output/diffmpm [--iterations 30]

A 2D fixed-corotated jelly (E = 10 kPa) (a body on two legs) stands on a floor with the "separate" condition
and Coulomb friction. Four actuators (the legs' and the body's halves) push their particles
apart or together along x: actuator k applies the force m_p a_k(t) sign(x_p - c_k) e_x, so
each actuator's forces sum to zero and the body can only move by pushing on the floor. The
activation is a_k(t) = A tanh(sum_j W_kj sin(omega t + 2 pi j / J) + b_k) (diffmpm's sine
controller without the feedback terms). The loss is minus the mean x of the particles after
the run; dL/d(controls) from one km.diff rollout gives dL/dW and dL/db by the chain rule, and
Adam updates them.

Writes loss.png (loss against iteration) and walker.png (the walker before and after, first
and last controller), and prints the loss of each iteration.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import Adam, plot_loss, pyplot  # noqa: E402


def walker(h):
    """Particle positions of a body on two legs, and for each particle its actuator (0..3)."""
    s = h / 2
    body = km.mpm.block([0.1, 0.1], [0.3, 0.16], s)
    legs = [km.mpm.block([x0, 0.0], [x0 + 0.05, 0.1], s) for x0 in (0.1, 0.25)]
    x = np.vstack([body] + legs)
    groups = np.concatenate([np.where(body[:, 0] < 0.2, 0, 1), np.full(len(legs[0]), 2), np.full(len(legs[1]), 3)])
    return x, groups


def make_sim(h, x):
    sim = km.mpm.Simulation((int(round(1 / h)), int(round(0.5 / h))), h, gravity=(0.0, -9.81),
                            boundary="separate", friction=1.5)
    sim.add_particles(x + [0.0, h], "elastic", density=1000.0, youngs_modulus=1e4, poisson_ratio=0.2)
    return sim


class Controller:
    """a_k(t) = A tanh(sum_j W_kj sin(omega t + 2 pi j / J) + b_k)."""

    def __init__(self, actuators, sines, amplitude, omega, seed=0):
        rng = np.random.default_rng(seed)
        self.W = rng.normal(0, 0.3, (actuators, sines))
        self.b = np.zeros(actuators)
        self.amplitude, self.omega, self.sines = amplitude, omega, sines

    def basis(self, t):
        return np.sin(self.omega * t[:, None] + 2 * np.pi * np.arange(self.sines) / self.sines)  # (steps, J)

    def activations(self, t):
        z = self.basis(t) @ self.W.T + self.b  # (steps, K)
        return self.amplitude * np.tanh(z), z


def forces_of(a, direction):
    """(steps, n, 2) forces from activations a (steps, K) and each particle's m_p sign (n, K)."""
    f = np.zeros((a.shape[0], direction.shape[0], 2))
    f[:, :, 0] = a @ direction.T
    return f


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/diffmpm"))
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--steps", type=int, default=600, help="MPM steps of the run")
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--cells", type=int, default=64, help="grid cells per metre")
    parser.add_argument("--learning-rate", type=float, default=0.1)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    h = 1.0 / args.cells
    x0, groups = walker(h)
    sim = make_sim(h, x0)
    s0 = sim.state()
    n, K = sim.count, 4
    centres = np.array([sim.x[groups == k, 0].mean() for k in range(K)])
    # direction[p, k] = m_p sign(x_p - c_k) for the particles of actuator k.
    direction = np.zeros((n, K))
    direction[np.arange(n), groups] = sim.mass * np.sign(sim.x[:, 0] - centres[groups])
    ctrl = Controller(K, 4, amplitude=40.0, omega=2 * np.pi * 5)
    t = np.arange(args.steps) * args.dt
    adam = Adam(args.learning_rate)
    losses, first_x = [], None
    for it in range(args.iterations):
        start = time.perf_counter()
        a, z = ctrl.activations(t)
        sim.set_state(s0)
        run = km.diff.rollout(sim, args.steps, args.dt, wrt=("controls",), controls=forces_of(a, direction),
                              checkpoints=int(2 * np.sqrt(args.steps)) + 1)
        x_end = run.outputs["x"]
        loss = -float(x_end[:, 0].mean())
        if first_x is None:
            first_x = x_end.copy()
        g = run.backward({"x": np.column_stack([np.full(n, -1.0 / n), np.zeros(n)])})["controls"]
        g_a = np.einsum("tn,nk->tk", g[:, :, 0], direction)  # dL/da (steps, K)
        g_z = g_a * ctrl.amplitude * (1 - np.tanh(z) ** 2)
        adam.step([ctrl.W, ctrl.b], [g_z.T @ ctrl.basis(t), g_z.sum(axis=0)])
        losses.append(loss)
        print(f"iteration {it:3d}  loss {loss:+.5f} (mean x {-loss:.4f} m)  {time.perf_counter() - start:.2f} s",
              flush=True)

    plot_loss(args.out / "loss.png", losses, "loss = -mean x after the run [m]",
              f"diffmpm on km.mpm: {n} particles, {args.steps} steps", log=False)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.scatter(*(x0 + [0, h]).T, s=1, c="0.7", label="start")
    ax.scatter(*first_x.T, s=1, c="tab:blue", label="first controller")
    ax.scatter(*run.outputs["x"].T, s=1, c="tab:red", label="last controller")
    ax.set_aspect("equal")
    ax.set_xlim(0, 0.7)
    ax.set_ylim(0, 0.3)
    ax.legend(loc="upper right", markerscale=6)
    fig.tight_layout()
    fig.savefig(args.out / "walker.png", dpi=120)
    plt.close("all")
    return losses


if __name__ == "__main__":
    main()
