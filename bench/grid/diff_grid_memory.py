"""Peak memory of the km.grid smoke-control gradient (diff_grid_bench.task) through km.diff, per
case in a fresh process: the resident set's high-water mark during rollout + backward above the
resident set just before the rollout (after one plain step, so the solver's forward arrays are
already counted as the simulation's own), in MiB and in states (u, v[, w], pressure, density),
beside km.diff's count of states held (`peak_states`). Everything the gradient allocates counts:
the states km.diff holds, the kept advection scratch, the adjoint's work arrays, the controls'
gradient (T steps, as large as the controls) and Python's copies.

    .venv/bin/python bench/grid/diff_grid_memory.py [--dims 2 3] [--schemes maccormack bfecc]

Linux only (/proc/self/clear_refs resets the high-water mark). Prints one line per case and a
SUMMARY line.
"""

from __future__ import annotations

import argparse
import gc
import subprocess
import sys
from pathlib import Path

import numpy as np

import kinema as km

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diff_grid_bench import TOL, kinema_fluid, task  # noqa: E402


def _status(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"/proc/self/status has no {key}")


def one(dim: int, scheme: str, checkpoints: int | None) -> str:
    km.set_num_threads(1)
    shape, steps = ((256, 256), 16) if dim == 2 else ((64, 64, 64), 9)
    h, dt, rho0, controls, weights, _ = task(shape, steps)
    sim = kinema_fluid(shape, h, rho0, scheme, 2 if scheme != "semi_lagrangian" else 1, TOL)
    s0 = sim.state()
    state = sum(v.nbytes for v in s0.values() if isinstance(v, np.ndarray))
    sim._diff_step(dt, controls[0], {})
    sim.set_state(s0)
    gc.collect()
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current resident set
    start = _status("VmRSS:")
    run = km.diff.rollout(sim, steps, dt, wrt=("controls",), controls=controls, checkpoints=checkpoints)
    after_rollout = _status("VmHWM:")
    run.backward({"density": weights})
    peak = _status("VmHWM:")
    name = "stored" if checkpoints is None else f"K={checkpoints}"
    return (f"{dim}D {'x'.join(map(str, shape))} {scheme} T={steps} {name}: peak above start "
            f"{(peak - start) / 2**20:.0f} MiB = {(peak - start) / state:.1f} states (rollout alone "
            f"{(after_rollout - start) / state:.1f}; the controls' gradient alone {controls.nbytes / state:.1f}); "
            f"peak_states {run.peak_states} (3 sqrt(T) = {3 * np.sqrt(steps):.1f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--schemes", nargs="+", default=["semi_lagrangian", "maccormack", "bfecc"])
    ap.add_argument("--case", nargs=3, metavar=("DIM", "SCHEME", "K"), help=argparse.SUPPRESS)
    opts = ap.parse_args()
    if opts.case:
        dim, scheme, k = opts.case
        print(one(int(dim), scheme, None if k == "none" else int(k)), flush=True)
        return
    summary = []
    for dim in opts.dims:
        steps = 16 if dim == 2 else 9
        for scheme in opts.schemes:
            for k in ("none", str(int(2 * np.sqrt(steps)))):
                out = subprocess.run([sys.executable, __file__, "--case", str(dim), scheme, k], capture_output=True,
                                     text=True, check=True).stdout.strip()
                print(out, flush=True)
                summary.append(f"{dim}D {scheme} {'stored' if k == 'none' else 'K=' + k} "
                               f"{out.split(' = ')[1].split(' states')[0]}")
    print("SUMMARY (peak memory above the start, in states): " + "; ".join(summary), flush=True)


if __name__ == "__main__":
    main()
