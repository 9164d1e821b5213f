"""Identifying a cantilever's Young's modulus field from its observed deflection, by gradient
descent through the simulation (km.diff over km.fem.Body).

    .venv/bin/python examples/diff_beam_identify.py --out demo_output/beam [--cells 24 4]
        [--steps 40] [--iterations 150]

A 2D beam (plane strain, neo-Hookean) clamped at x = 0 sags under gravity. The "true" modulus
falls from 3 E0 at the root to E0/2 at the tip; the observation is the beam's shape after
`steps` heavily damped implicit steps (close to its static deflection). Starting from a uniform
guess, the modulus of each column of cells, E_j = exp(theta_j), is fitted to the observed shape by
Adam on L(theta) = |x_T(theta) - x_obs|^2 / |x_obs - rest|^2, the gradient dL/dtheta from one
reverse pass (km.diff.rollout(..., wrt="youngs_modulus"): one adjoint solve per step with the
converged Newton Hessian). Writes loss.png (loss against iteration) and modulus.png (true and
fitted modulus along the beam) and prints the relative error of the fitted field.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))  # examples/_diffplot.py, from any directory
from _diffplot import Adam, plot_loss, pyplot  # noqa: E402

E0, NU, RHO, DAMPING = 2e5, 0.3, 500.0, 40.0


def true_modulus(centres, length):
    return E0 * (3.0 - 2.5 * centres[:, 0] / length)


def make_beam(cells, length, height):
    V, T = km.fem.rectangle_mesh([0, 0], [length, height], cells)
    fixed = np.flatnonzero(V[:, 0] < 1e-9)
    centres = V[T].mean(axis=1)
    column = np.minimum((centres[:, 0] / length * cells[0]).astype(int), cells[0] - 1)
    return V, T, fixed, centres, column


def simulate(V, T, fixed, E, steps, dt):
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=E, poisson_ratio=NU, density=RHO,
                       fixed=fixed, gravity=(0, -9.81), damping=DAMPING)
    return body, km.diff.rollout(body, steps, dt, wrt=("youngs_modulus",), tol=1e-9)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/beam"))
    parser.add_argument("--cells", type=int, nargs=2, default=(24, 4))
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--dt", type=float, default=0.02)
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--rate", type=float, default=0.08, help="Adam step on log E")
    args = parser.parse_args(argv)
    length, height = 2.0, 0.25
    cells = tuple(args.cells)
    V, T, fixed, centres, column = make_beam(cells, length, height)

    E_true = true_modulus(centres, length)
    _, observed = simulate(V, T, fixed, E_true, args.steps, args.dt)
    x_obs = observed.outputs["x"]
    scale = float(((x_obs - V) ** 2).sum())

    theta = np.full(cells[0], np.log(E0))  # log modulus per column of cells
    adam = Adam(args.rate)
    losses = []
    for it in range(1, args.iterations + 1):
        E = np.exp(theta[column])
        _, run = simulate(V, T, fixed, E, args.steps, args.dt)
        r = run.outputs["x"] - x_obs
        losses.append(float((r ** 2).sum()) / scale)
        g_E = run.backward({"x": 2 * r / scale})["youngs_modulus"]
        g = np.bincount(column, weights=g_E * E, minlength=cells[0])  # dL/dtheta_j
        adam.step([theta], [g])
        if it == 1 or it % 10 == 0 or it == args.iterations:
            print(f"iteration {it:3d}: loss {losses[-1]:.3e}")

    E_fit = np.exp(theta)
    E_col = np.array([E_true[column == j].mean() for j in range(cells[0])])
    error = float(np.linalg.norm(E_fit - E_col) / np.linalg.norm(E_col))
    print(f"loss {losses[0]:.3e} -> {losses[-1]:.3e}; relative error of the fitted modulus {error:.3f}")

    args.out.mkdir(parents=True, exist_ok=True)
    plot_loss(args.out / "loss.png", losses, "loss |x_T - x_obs|^2 (relative)", "beam modulus identification",
              first=1)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    xc = (np.arange(cells[0]) + 0.5) * length / cells[0]
    ax.plot(xc, E_col / 1e3, "k-", label="true")
    ax.plot(xc, E_fit / 1e3, "o", ms=4, label="fitted")
    ax.axhline(E0 / 1e3, color="0.6", ls=":", label="initial guess")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("E [kPa]")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "modulus.png", dpi=120)
    plt.close(fig)
    return losses, error


if __name__ == "__main__":
    main()
