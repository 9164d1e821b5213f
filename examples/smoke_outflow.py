"""Smoke from an inflow source in a box with a closed and with an open top (km.grid), side by side.

    .venv/bin/python examples/smoke_outflow.py --out demo_output/outflow [--cells 64] [--seconds 6]

A jet of smoke (a source imposing density and an upward velocity before every step,
``Fluid.add_source``) rises by buoyancy. In the closed box the smoke has nowhere to go and fills
it; with ``open="y+"`` (pressure p = 0 on the top, fluid free to cross it) the plume leaves
through the top and fresh air is drawn in. Writes outflow.png (density of both at the end) and
prints the smoke mass in each box once per second.
"""

import argparse
from pathlib import Path

import numpy as np

import kinema as km


def run(open_sides, cells, seconds):
    h = 1.0 / cells
    fluid = km.grid.Fluid((cells, cells), h, density=True, buoyancy=(-1.0, 0.0), open=open_sides,
                          vorticity_confinement=0.1)
    jet = np.linalg.norm(fluid.cell_centers() - (0.5, 0.12), axis=-1) < 0.08
    fluid.add_source(jet, density=1.0, velocity=(0.0, 1.0))
    masses = []
    for _ in range(int(round(seconds))):
        fluid.advance(1.0, cfl=1.0)
        masses.append(float(fluid.density.sum() * h * h))
    return fluid, masses


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/outflow"))
    parser.add_argument("--cells", type=int, default=64, help="cells per axis of the unit box")
    parser.add_argument("--seconds", type=float, default=6.0)
    args = parser.parse_args(argv)

    results = {}
    for label, sides in (("closed box", ()), ("open top", ("y+",))):
        fluid, masses = run(sides, args.cells, args.seconds)
        results[label] = fluid
        print(f"{label:>10}: smoke mass per second " + " ".join(f"{m:.3f}" for m in masses))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(8, 4.2))
    for ax, (label, fluid) in zip(axes, results.items()):
        ax.imshow(fluid.density.T, origin="lower", extent=(0, 1, 0, 1), cmap="inferno", vmin=0, vmax=1)
        ax.set_title(f"{label}, t = {fluid.time:.1f} s")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    path = args.out / "outflow.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"wrote {path}")
    return results


if __name__ == "__main__":
    main()
