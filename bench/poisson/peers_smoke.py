"""Runs every peer solver once and prints its time by phase, iterations and verified residual.

    .venv/bin/python bench/poisson/peers_smoke.py            # small: 2D 128^2 and 3D 32^3 (about a minute)
    .venv/bin/python bench/poisson/peers_smoke.py --full     # the sizes of issue 2, section 5 (minutes)
    .venv/bin/python bench/poisson/peers_smoke.py --only taichi pyamg --threads 2

Problem: -lap u = f, cell-centred, Dirichlet (ghost = -u), h = 1/N, f = poisson_rhs(kind="random")
(seed 0). The matrix peers get laplacian_matrix(shape, h) and f; Taichi gets b = h^2 f on its
own vertex-centred operator (see peers.taichi_mgpcg). Every call goes through
harness.measure (repeated when other processes loaded the machine) and is appended to
bench/out/peers_smoke.csv. The figures are for orientation: the side-by-side comparison
belongs on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402
import peers  # noqa: E402

#: (peer, shape, tol) runs of the quick check.
SMALL_RUNS = (
    ("pyamg", (128, 128), 1e-8),
    ("spsolve", (128, 128), None),
    ("cholmod", (128, 128), None),
    ("taichi", (128, 128), 1e-6),
    ("pyamg", (32, 32, 32), 1e-8),
    ("spsolve", (32, 32, 32), None),
    ("cholmod", (32, 32, 32), None),
    ("taichi", (32, 32, 32), 1e-6),
)

#: The peers' sizes and tolerances named in issue 2, section 5.
FULL_RUNS = (
    ("taichi", (128, 128, 128), 1e-6),
    ("pyamg", (1024, 1024), 1e-8),
    ("pyamg", (128, 128, 128), 1e-6),
    ("cholmod", (1024, 1024), None),
    ("spsolve", (1024, 1024), None),
)

#: Phase reported as the figure of each peer.
FIGURE_PHASE = {"pyamg": "total", "spsolve": "total", "cholmod": "total", "taichi": "solve"}


def run_peer(peer: str, shape, tol, threads: int) -> peers.PeerResult:
    """Solves the benchmark problem of `shape` with `peer` (phases timed inside the peer)."""
    h = 1.0 / shape[0]
    f = peers.poisson_rhs(shape, h, kind="random")
    if peer == "taichi":
        return peers.taichi_mgpcg(h * h * f, tol, threads=threads)
    matrix = peers.laplacian_matrix(shape, h, bc="dirichlet")
    if peer == "pyamg":
        return peers.pyamg_sa_cg(matrix, f, tol)
    if peer == "spsolve":
        return peers.scipy_spsolve(matrix, f)
    if peer == "cholmod":
        return peers.sksparse_cholmod(matrix, f, threads=threads)
    raise ValueError(f"peer: unknown {peer!r}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the issue's sizes instead of the small ones")
    parser.add_argument("--only", nargs="+", choices=sorted(FIGURE_PHASE), help="run only these peers")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="threads for Taichi and CHOLMOD's BLAS (PyAMG and SciPy are serial)")
    parser.add_argument("--max-tries", type=int, default=3, help="timed calls at most when disturbed")
    parser.add_argument("--csv", default=str(Path(__file__).resolve().parents[1] / "out" / "peers_smoke.csv"))
    args = parser.parse_args(argv)

    runs = [r for r in (FULL_RUNS if args.full else SMALL_RUNS) if not args.only or r[0] in args.only]
    recorder = harness.Recorder(args.csv, benchmark="peers_full" if args.full else "peers_smoke",
                                threads=args.threads)
    print(f"commit {recorder.commit}, threads {args.threads}, csv {args.csv}")
    failed = 0
    for peer, shape, tol in runs:
        size = harness.format_size(shape)
        started = time.perf_counter()
        try:
            m = harness.measure(lambda: run_peer(peer, shape, tol, args.threads), max_tries=args.max_tries,
                                figure=lambda result, wall: result.seconds[FIGURE_PHASE[peer]])
        except (peers.VerificationError, ImportError, MemoryError) as error:
            print(f"{peer:8s} {size:12s} FAILED: {type(error).__name__}: {error}")
            failed += 1
            continue
        result = m.value
        phases = ", ".join(f"{k} {v:.3f}" for k, v in result.seconds.items())
        threads = args.threads if peer in ("taichi", "cholmod") else 1
        notes = {"tol": tol if tol is not None else "direct", "bc": "dirichlet", "rhs": "random",
                 **{f"t_{k}": v for k, v in result.seconds.items()}}
        if peer == "cholmod":
            notes["blas"] = peers.blas_description()
        recorder.record(peer, shape, m.seconds, error=result.residual, iterations=result.iterations,
                        threads=threads, measurement=m, notes=notes)
        print(f"{peer:8s} {size:12s} {FIGURE_PHASE[peer]} {m.seconds:8.3f} s  [{phases}]  "
              f"iterations {result.iterations}  residual {result.residual:.2e}  "
              f"other_load {m.other_load:.2f}{' DISTURBED' if m.disturbed else ''}  repeats {m.repeats}  "
              f"(wall incl. repeats {time.perf_counter() - started:.1f} s)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
