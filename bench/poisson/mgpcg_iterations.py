"""MGPCG iteration counts to tol 1e-8 against the grid size (issue 2: they must stay flat).

    .venv/bin/python bench/poisson/mgpcg_iterations.py [--thin-walls]

Random f (seed 4), h = 1/N, Dirichlet and Neumann (mean removed); then a solid disk/ball of
radius 0.2 at 0.4 in every coordinate. Prints one line per grid; counts, not times, so the
figures do not depend on the machine's load. --thin-walls instead counts the iterations (and
times both solves) with walls one cell thick across the domain, a known weakness of the
hierarchy (bench/RESULTS.md, "Thin walls").
"""

import sys
import time

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


def thin_walls():
    rng = np.random.default_rng(3)
    for dim, sizes in [(2, [64, 256, 1024]), (3, [32, 64, 128])]:
        for n in sizes:
            shape = (n,) * dim
            for kind in ("none", "wall at j = 7", "wall at j = n/2+1 with a gap", "two walls", "box", "sphere"):
                solid = np.zeros(shape, bool)
                if kind == "wall at j = 7":
                    solid[:, 7] = True
                elif kind == "wall at j = n/2+1 with a gap":
                    solid[:, n // 2 + 1] = True
                    solid[: n // 4, n // 2 + 1] = False
                elif kind == "two walls":
                    solid[:, 5] = True
                    solid[:, 3 * n // 4 + 1] = True
                elif kind == "box":
                    solid[n // 3 : n // 2, n // 4 : n // 2] = True
                elif kind == "sphere":
                    g = (np.indices(shape) + 0.5) / n - 0.5
                    solid = (g**2).sum(0) < 0.3**2
                f = rng.standard_normal(shape)
                f[solid] = 0
                start = time.perf_counter()
                counts = [km.poisson.solve(f, 1.0 / n, bc, tol=1e-8, solid=solid if solid.any() else None,
                                           rhs_mean="remove")[1].iterations
                          for bc in ("dirichlet", "neumann")]
                print(f"{shape} {kind}: dirichlet {counts[0]}, neumann {counts[1]} "
                      f"({time.perf_counter() - start:.2f} s for both)", flush=True)


if __name__ == "__main__":
    thin_walls() if "--thin-walls" in sys.argv[1:] else main()
