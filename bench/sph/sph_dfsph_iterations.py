"""DFSPH solver iterations, density errors and time per step on the dam break of sph_bench.py,
for one set of km.sph.Fluid keyword arguments (kinema only; no harness: a quick probe whose
figures compare only with other calls of it on an equally quiet machine).

    python bench/sph/sph_dfsph_iterations.py                     # 150k particles, 20 steps
    python bench/sph/sph_dfsph_iterations.py 150000 20 '{"warm_start": 0.75}'
    python bench/sph/sph_dfsph_iterations.py 60000 10 '{"tol": 1e-4, "divergence_tol": 1e-4}'

The run starts as sph_bench.py's does (round(START / dt) steps from rest at the DFSPH step of
sph_bench.timed_dt, the surge front's CFL step) and prints, per step on average: the
constant-density and divergence-free iterations, the density error the solver reached
(predicted), the mean compression recomputed at the final positions, and the CPU and wall
milliseconds.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import sph_bench as sb  # noqa: E402


def main():
    import kinema as km

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 150_000
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 20
    kw = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
    x, s, domain = sb.scene(n)
    fluid = km.sph.Fluid(x, s, method="dfsph", gravity=(0, -9.81, 0), domain=domain,
                         **{"tol": 1e-3, "divergence_tol": 1e-3, **kw})
    dt = sb.timed_dt(n, "dfsph", 1e-3)[0]
    for _ in range(max(1, round(sb.START / dt))):  # sph_bench.py's start-up (started_fluid)
        fluid.step(dt)
    density_its, divergence_its, errors = [], [], []
    split = np.zeros(3)
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(steps):
        st = fluid.step(dt)
        density_its.append(st.iterations)
        divergence_its.append(st.divergence_iterations)
        errors.append(st.density_error)
        split += (st.search_seconds, st.kernel_seconds, st.solve_seconds)
    cpu = (time.process_time() - cpu) / steps * 1e3
    wall = (time.perf_counter() - wall) / steps * 1e3
    print(f"n={fluid.n} {kw} dt={dt:.3g}: density iterations {np.mean(density_its):.2f}, divergence "
          f"{np.mean(divergence_its):.2f}, solver error {np.mean(errors):.2e}, compression at the end "
          f"{fluid.density_error():.2e}, {cpu:.1f} CPU ms / {wall:.1f} ms per step (search / kernel pass / "
          f"solves {' / '.join(f'{1e3 * t / steps:.1f}' for t in split)} ms; {st.neighbor_count} neighbour entries)")


if __name__ == "__main__":
    main()
