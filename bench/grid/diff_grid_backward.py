"""The CPU time of km.diff's backward alone (one thread, min of --reps, a fresh rollout before
each) for the task of diff_grid_cpu.py, MacCormack RK2: 2D 256^2 (T = 16) or 3D 64^3 (T = 9),
stored or checkpointed. Alternate it between two builds, process by process, for an A/B of the
backward that the forward's timing does not blur:

    PYTHONPATH=<main's site-packages> .venv/bin/python bench/grid/diff_grid_backward.py --dims 3 --checkpoints 6
    .venv/bin/python bench/grid/diff_grid_backward.py --dims 3 --checkpoints 6

Prints one line: the case, the backward's seconds and the gradient's directional derivative in
hex (equal between builds that give the same bits).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diff_grid_cpu import setup  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dims", type=int, choices=(2, 3), default=3)
    ap.add_argument("--checkpoints", type=int, default=None, help="K (default: every state stored)")
    ap.add_argument("--reps", type=int, default=3)
    opts = ap.parse_args()
    km.set_num_threads(1)
    shape, steps = ((256, 256), 16) if opts.dims == 2 else ((64, 64, 64), 9)
    sim, s0, _, dt, controls, weights, direction = setup(shape, steps, "maccormack", 2, 1e-10)
    best, g = float("inf"), None
    for _ in range(opts.reps):
        sim.set_state(s0)
        run = km.diff.rollout(sim, steps, dt, wrt=("controls",), controls=controls, checkpoints=opts.checkpoints)
        t = time.process_time()
        g = run.backward({"density": weights})["controls"]
        best = min(best, time.process_time() - t)
    print(f"{opts.dims}D maccormack checkpoints={opts.checkpoints}: backward CPU {best:.3f} s, "
          f"<g, d> {float(np.sum(g * direction)).hex()}", flush=True)


if __name__ == "__main__":
    main()
