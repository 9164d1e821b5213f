"""One-thread CPU time per substep of kinema's mpm88 and mpm128 scenes, for A/B runs of builds.

The scenes are those of `mpm_bench.py taichi` (kinema_scene) from random initial particles in
the examples' shapes (no Taichi needed), on a fixed team of one thread; the figure is the best
of 5 blocks of 200 substeps after 300 warm-up substeps, in process CPU time (the machine is
shared). Usage (the kinema imported is the interpreter's):

    .venv/bin/python bench/mpm/mpm_lanes_ab.py                          # this build, AVX2 lanes
    KINEMA_SIMD=baseline .venv/bin/python bench/mpm/mpm_lanes_ab.py     # this build, scalar path
    /work/main/.venv/bin/python bench/mpm/mpm_lanes_ab.py               # another build
"""
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).parent))
from mpm_bench import kinema_scene  # noqa: E402


def main():
    km.set_num_threads(1)
    rng = np.random.default_rng(1)
    out = []
    for kind in ("mpm88", "mpm128"):
        if kind == "mpm88":
            n = 8192
            start = dict(x=rng.random((n, 2)) * 0.4 + 0.2, v=np.zeros((n, 2)), n_grid=128)
            dt = 2e-4
        else:
            g = 3000  # three squares: water, jelly, snow (the example's layout)
            x = np.concatenate([rng.random((g, 2)) * 0.2 + [0.3 + 0.1 * i, 0.05 + 0.32 * i] for i in range(3)])
            start = dict(x=x, v=np.zeros((3 * g, 2)), n_grid=128, gravity=[0, -50.0],
                         material=np.repeat([0, 1, 2], g))
            dt = 1e-4
        sim = kinema_scene(kind, start, adapt_threads=False)
        for _ in range(300):
            sim.step(dt)
        best = float("inf")
        for _ in range(5):
            t0 = time.process_time()
            for _ in range(200):
                sim.step(dt)
            best = min(best, (time.process_time() - t0) / 200)
        out.append(f"{kind} {best * 1e3:.3f} ms")
    print("one thread, CPU time per substep: " + " | ".join(out))


if __name__ == "__main__":
    main()
