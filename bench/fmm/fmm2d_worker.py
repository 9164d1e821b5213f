"""Runs Flatiron's FMM2D (pip fmm2dpy, `rfmm2d`) on points saved by bench/fmm/fmm_bench.py.

Runs in its own virtual environment with numpy<2 (fmm2dpy's only release is built against
numpy 1.x); bench/fmm/fmm_bench.py creates it (bench/out/venv-fmm2d) and calls this script as a
subprocess, so nothing of FMM2D is imported into kinema's environment. Usage:

    python fmm2d_worker.py DIR EPS [EPS ...]

DIR holds sources.npy (N, 2), charges.npy (N,), subset.npy (indices where the answer is
checked). For each eps, rfmm2d computes the potential and gradient at the sources (self term
left out, pg=2) with OMP_NUM_THREADS threads; the seconds of the call itself (timed around it,
no I/O) and the potential and gradient at `subset` go to DIR/fmm2d_<eps>.npz, and one JSON
line per eps to stdout. rfmm2d's kernel is log|x - y| (FMM2D documentation, "Laplace FMM":
real charges c_j, u(x) = sum_j c_j log|x - x_j|), the same as km.fmm.laplace2d.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import fmm2dpy


def main():
    folder = Path(sys.argv[1])
    sources = np.load(folder / "sources.npy")
    charges = np.load(folder / "charges.npy")
    subset = np.load(folder / "subset.npy")
    src = np.asfortranarray(sources.T)
    for text in sys.argv[2:]:
        eps = float(text)
        start = time.perf_counter()
        out = fmm2dpy.rfmm2d(eps=eps, sources=src, charges=charges, pg=2)
        seconds = time.perf_counter() - start
        pot = np.asarray(out.pot)[subset]
        grad = np.asarray(out.grad)[:, subset].T
        np.savez(folder / f"fmm2d_{text}.npz", pot=pot, grad=grad, seconds=seconds)
        print(json.dumps({"eps": eps, "seconds": seconds, "ier": int(getattr(out, "ier", 0))}), flush=True)


if __name__ == "__main__":
    main()
