"""km.sph work-precision: the 2D dam break of Martin and Moyce (1952) swept over the particle
spacing (both methods) and the DFSPH solver tolerance, against two errors:

* front error: the largest relative deviation of the surge front Z = z/a from the experiment
  at its recorded times T = t sqrt(2 g / a) (up to Z ~ 5), and
* density error: the mean compression max(rho/rho0 - 1, 0) averaged over the run's frames.

    python bench/sph/sph_work_precision.py            # ratios 10, 20, 40 particles across the column
    python bench/sph/sph_work_precision.py --quick    # ratios 10, 20
    python bench/sph/sph_work_precision.py --settings # DFSPH warm start and Verlet skin counts

Each run is timed with bench/common/harness.py (the load of other processes is recorded per run).
CSV: bench/out/sph_work_precision.csv; plot: bench/out/sph_work_precision.png.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402
from sph_bench import MEASURE, OUT, plot_and_report  # noqa: E402

G = 9.81
A = 0.1  # column width [m]; height 2a, tank 8a x 3a


def dam_break(method, ratio, tol):
    """Runs the column with `ratio` particles across; returns (front error, density error, steps)."""
    import kinema as km

    data = km.sph.martin_moyce()
    s = A / ratio
    x = km.sph.block([0, 0], [A, 2 * A], s)
    fluid = km.sph.Fluid(x, s, method=method, domain=([0, 0], [8 * A, 3 * A]), tol=tol,
                         divergence_tol=tol)
    fronts, compression, steps = [], [], 0
    for T, _ in data:
        steps += fluid.advance(T / np.sqrt(2 * G / A) - fluid.time)
        # The front: the (ratio/4)-th farthest particle (spray ahead of the surge is not it).
        fronts.append(np.sort(fluid.x[:, 0])[-max(3, ratio // 4)] / A)
        compression.append(fluid.density_error())
    front_error = float(np.max(np.abs(np.array(fronts) / data[:, 1] - 1)))
    if not np.isfinite(fluid.x).all():
        raise AssertionError(f"{method} ratio {ratio}: non-finite positions; not recording")
    return front_error, float(np.mean(compression)), steps


def settings():
    """Solver iterations per step against warm_start, and grid searches against neighbor_skin,
    on the column at 20 particles across, in CFL steps to t = 0.2 s (counts, not times)."""
    import kinema as km

    s = A / 20
    x = km.sph.block([0, 0], [A, 2 * A], s)
    domain = ([0, 0], [8 * A, 3 * A])
    for warm in (0.0, 0.5, 0.75, 1.0):
        fluid = km.sph.Fluid(x, s, domain=domain, warm_start=warm)
        its = div = steps = 0
        try:
            while fluid.time < 0.2:
                st = fluid.step(fluid.stable_dt())
                its, div, steps = its + st["iterations"], div + st["divergence_iterations"], steps + 1
            print(f"dfsph warm_start={warm}: {steps} steps, {its / steps:.2f} density and "
                  f"{div / steps:.2f} divergence iterations per step")
        except km.DivergenceError:
            print(f"dfsph warm_start={warm}: diverged at step {steps}")
    for method in ("wcsph", "dfsph"):
        for skin in (0.0, 0.2):
            fluid = km.sph.Fluid(x, s, method=method, domain=domain, neighbor_skin=skin)
            searches = steps = 0
            while fluid.time < 0.2:
                searches += fluid.step(fluid.stable_dt())["neighbor_rebuild"]
                steps += 1
            print(f"{method} neighbor_skin={skin}: {searches} grid searches in {steps} steps")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--settings", action="store_true", help="warm start and skin counts only")
    p.add_argument("--loaded", action="store_true", help="busy machine: at most 2 tries per run")
    p.add_argument("--threads", type=int, default=harness.default_threads())
    args = p.parse_args(argv)
    import kinema as km

    km.set_num_threads(args.threads)
    if args.loaded:
        MEASURE.update(max_tries=2, quiet_timeout=1.0)
    if args.settings:
        settings()
        return 0
    ratios = [10, 20] if args.quick else [10, 20, 40]
    OUT.mkdir(exist_ok=True)
    csv_path = OUT / "sph_work_precision.csv"
    rec = harness.Recorder(csv_path, "sph_dambreak2d_work_precision", threads=args.threads)
    runs = [("wcsph", r, 1e-3) for r in ratios] + [("dfsph", r, 1e-3) for r in ratios]
    runs += [("dfsph", ratios[1], t) for t in (1e-2, 1e-4)]
    print(f"threads {args.threads}, commit {harness.git_commit()}")
    print(f"{'method':6s} {'ratio':>5s} {'tol':>7s} {'seconds':>8s} {'steps':>6s} {'front err':>9s} "
          f"{'density err':>11s} {'other load':>10s}")
    for method, ratio, tol in runs:
        m = harness.measure(lambda: dam_break(method, ratio, tol), min_of=1, **MEASURE)
        front, density, steps = m.value
        name = f"kinema-{method}" + (f"-tol{tol:g}" if method == "dfsph" else "")
        rec.record(name, ratio, m.seconds, error=front, iterations=steps, measurement=m,
                   notes={"density_error": f"{density:.3g}", "spacing": A / ratio, "tol": tol})
        print(f"{method:6s} {ratio:5d} {tol if method == 'dfsph' else float('nan'):7.0e} "
              f"{m.seconds:8.2f} {steps:6d} {front:9.3f} {density:11.2e} {m.other_load:10.2f}")
    plot_and_report(csv_path, "sph_work_precision.png", "sph_dambreak2d_work_precision")
    return 0


if __name__ == "__main__":
    sys.exit(main())
