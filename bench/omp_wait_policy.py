"""A small MGPCG solve (512x256, Neumann, solid disk, tol 1e-10), best of 5: run it with and
without OMP_WAIT_POLICY=passive, on a quiet and on a busy machine, to see the trade-off the
README describes.

    .venv/bin/python bench/omp_wait_policy.py
    OMP_WAIT_POLICY=passive .venv/bin/python bench/omp_wait_policy.py
"""

import os
import time

import numpy as np

import kinema as km


def main():
    n = 256
    h = 1.0 / n
    X, Y = np.meshgrid((np.arange(2 * n) + 0.5) * h, (np.arange(n) + 0.5) * h, indexing="ij")
    solid = (X - 1.0) ** 2 + (Y - 0.5) ** 2 < 0.15**2
    f = np.random.default_rng(0).standard_normal(X.shape)
    f[solid] = 0
    f[~solid] -= f[~solid].mean()
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        _, info = km.poisson.solve(f, h, "neumann", tol=1e-10, solid=solid)
        best = min(best, time.perf_counter() - t0)
    print(f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(default)')} threads "
          f"{km.get_num_threads()}: {info.iterations} iterations, best {best:.4f} s, "
          f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
