"""MGPCG iteration counts to tol 1e-8 against the grid size (issue 2: they must stay flat).

    .venv/bin/python bench/mgpcg_iterations.py

Random f (seed 4), h = 1/N, Dirichlet and Neumann (mean removed); then a solid disk/ball of
radius 0.2 at 0.4 in every coordinate. Prints one line per grid; counts, not times, so the
figures do not depend on the machine's load.
"""

import numpy as np

import kinema as km


def main():
    rng = np.random.default_rng(4)
    for shape in [(64, 64), (128, 128), (256, 256), (512, 512), (1024, 1024), (2048, 2048),
                  (32,) * 3, (64,) * 3, (128,) * 3, (256,) * 3]:
        f = rng.standard_normal(shape)
        counts = [km.poisson.solve(f, 1.0 / shape[0], bc, tol=1e-8, rhs_mean="remove")[1].iterations
                  for bc in ("dirichlet", "neumann")]
        print(f"{shape}: dirichlet {counts[0]}, neumann {counts[1]}", flush=True)
    for shape in [(64, 64), (256, 256), (1024, 1024), (32,) * 3, (64,) * 3, (128,) * 3]:
        h = 1.0 / shape[0]
        X = np.meshgrid(*[(np.arange(n) + 0.5) * h for n in shape], indexing="ij")
        solid = sum((x - 0.4) ** 2 for x in X) < 0.2**2
        f = rng.standard_normal(shape)
        counts = [km.poisson.solve(f, h, bc, tol=1e-8, solid=solid, rhs_mean="remove")[1].iterations
                  for bc in ("dirichlet", "neumann")]
        print(f"{shape} with an obstacle: dirichlet {counts[0]}, neumann {counts[1]}", flush=True)


if __name__ == "__main__":
    main()
