"""Two installed builds of kinema side by side, one workload per method, through the public API
only: the before/after check of a refactor that must change neither speed nor results.

    .venv/bin/python bench/shape_compare.py BEFORE_PYTHON AFTER_PYTHON [--repeats 5] [--steps 10]
        [--only sph_wcsph grid_smoke ...] [--threads 2] [--out bench/out/shape_compare]
    .venv/bin/python bench/shape_compare.py --table bench/out/shape_compare.csv   # its table again

BEFORE_PYTHON / AFTER_PYTHON are the interpreters of two virtual environments, each with one
build of kinema installed (bench/README.md shows how to make the "before" one from a git
worktree of the older commit). Every (repeat, workload, build) is a fresh process running
this file with --worker: it builds the workload, takes one untimed step (first-touch, lazy
factorisations), times --steps more one by one and saves the final state. The builds alternate
within each repeat and swap order between repeats, so that a shared machine's load falls on
both alike; each run records the CPU load of other processes over its timed window
(bench/common/harness.py) and is run again, after waiting for a quiet moment, when that load
exceeds --max-load.

The figure per run is the median of its per-step wall times; per workload and build the median
over the repeats, with the spread (min-max) and the highest load, and beside it the median CPU
time per step (all threads), which other processes' load disturbs much less than the wall time. The final states of the
two builds are compared: "bitwise" when every array is identical, else the largest difference
relative to the array's largest magnitude. Writes OUT.csv (one row per run) and OUT.md (the
table) and prints the table.

Workloads (float64, the default thread count of --threads):
  sph_wcsph, sph_dfsph   3D dam break, ~23k particles, box walls, gravity, dt = stable_dt()
  grid_smoke             2D 256^2 smoke with density, temperature, buoyancy, vorticity confinement
  grid_smoke_3d          3D 48^3 of the same
  poisson_mgpcg          3D 96^3 Dirichlet Poisson solve to tol 1e-8 (one solve per "step")
  massspring_cloth       64 x 64 implicit cloth pinned at two corners, dt 1/60
  fem_neohookean         neo-Hookean beam of 32 x 8 x 8 cells clamped at one end, implicit, dt 1/60
  mpm                    3D MLS-MPM: an elastic block and water on a 32^3 grid
  fmm_laplace2d          200k sources, eps 1e-10 (one evaluation per "step")
  fmm_laplace3d          100k sources, eps 1e-6 (one evaluation per "step")
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "common"))  # harness.py
import harness  # noqa: E402


# Workloads: each returns (step, final) where step() advances once and final() returns the
# state to compare, a dict of arrays. Only the public API (API.md) is used, so that a build
# whose internals moved runs the same code.

def _sph(method):
    import numpy as np

    import kinema as km

    s = 0.02
    lower, upper = np.zeros(3), np.array([1.6, 0.8, 0.6])
    x = km.sph.block([s, s, s], [0.5, 0.5, 0.6 - s], s)
    fluid = km.sph.Fluid(x, s, method=method, gravity=(0.0, -9.81, 0.0), domain=(lower, upper),
                         viscosity=1e-6)
    dt = fluid.stable_dt()
    return (lambda: fluid.step(dt)), (lambda: {"x": np.array(fluid.x), "v": np.array(fluid.v)}), len(x)


def _grid(shape):
    import numpy as np

    import kinema as km

    d = len(shape)
    h = 1.0 / shape[0]
    g = [0.0] * d
    g[1] = -9.81
    f = km.grid.Fluid(shape, h, density=True, temperature=True, buoyancy=(0.1, 8.0), gravity=g,
                      vorticity_confinement=0.15)
    centres = np.meshgrid(*[(np.arange(n) + 0.5) * h for n in shape], indexing="ij")
    src = (np.abs(centres[0] - 0.5) < 0.1) & (centres[1] < 0.1)
    if d == 3:
        src &= np.abs(centres[2] - 0.5) < 0.1

    def step():
        f.density[src] = 1.0
        f.temperature[src] = 1.0
        f.step(1.0 / 120)

    def final():
        out = {name: np.array(getattr(f, name)) for name in ("u", "v", "density", "temperature", "pressure")}
        if d == 3:
            out["w"] = np.array(f.w)
        return out

    return step, final, int(np.prod(shape))


def _poisson(n):
    import numpy as np

    import kinema as km

    h = 1.0 / n
    rng = np.random.default_rng(4)
    f = rng.standard_normal((n, n, n))
    result = {}

    def step():
        result["u"], _ = km.poisson.solve(f, h, bc="dirichlet", method="mgpcg", tol=1e-8)

    return step, (lambda: result), n**3


def _cloth(n):
    import numpy as np

    import kinema as km

    x, springs = km.massspring.cloth(n, n, 1.0)
    x[:, 2] = 1.0
    system = km.massspring.System(x, springs, stiffness=2000.0, mass=0.2 / n**2, damping=0.02,
                                  fixed=[0, (n - 1) * n], gravity=(0.0, 0.0, -9.81))
    return (lambda: system.step(1.0 / 60)), (lambda: {"x": np.array(system.x), "v": np.array(system.v)}), n * n


def _fem():
    import numpy as np

    import kinema as km

    V, T = km.fem.box_mesh([0, 0, 0], [1.0, 0.25, 0.25], (32, 8, 8))
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=2e5, poisson_ratio=0.4, density=1000.0,
                       fixed=np.flatnonzero(V[:, 0] < 1e-12), gravity=(0.0, 0.0, -9.81), damping=0.5)
    return (lambda: body.step(1.0 / 60)), (lambda: {"x": np.array(body.x), "v": np.array(body.v)}), len(T)


def _mpm():
    import numpy as np

    import kinema as km

    n = 32
    h = 1.0 / n
    sim = km.mpm.Simulation((n, n, n), h, gravity=(0.0, -9.81, 0.0), boundary="slip")
    s = h / 2
    sim.add_particles(km.mpm.block([0.1, 0.1, 0.1], [0.4, 0.5, 0.4], s), "water", density=1000.0,
                      youngs_modulus=1e5)
    sim.add_particles(km.mpm.block([0.55, 0.3, 0.55], [0.8, 0.55, 0.8], s), "elastic", density=500.0,
                      youngs_modulus=2e5, poisson_ratio=0.3)
    dt = 2e-4
    return (lambda: sim.step(dt)), (lambda: {"x": np.array(sim.x), "v": np.array(sim.v), "F": np.array(sim.F)}), \
        len(sim.x)


def _fmm(dim, n, eps):
    import numpy as np

    import kinema as km

    rng = np.random.default_rng(7)
    x = rng.random((n, dim))
    q = rng.standard_normal(n)
    fn = km.fmm.laplace2d if dim == 2 else km.fmm.laplace3d
    result = {}

    def step():
        result["phi"] = fn(x, q, eps=eps)

    return step, (lambda: result), n


WORKLOADS = {
    "sph_wcsph": lambda: _sph("wcsph"),
    "sph_dfsph": lambda: _sph("dfsph"),
    "grid_smoke": lambda: _grid((256, 256)),
    "grid_smoke_3d": lambda: _grid((48, 48, 48)),
    "poisson_mgpcg": lambda: _poisson(96),
    "massspring_cloth": lambda: _cloth(64),
    "fem_neohookean": _fem,
    "mpm": _mpm,
    "fmm_laplace2d": lambda: _fmm(2, 200_000, 1e-10),
    "fmm_laplace3d": lambda: _fmm(3, 100_000, 1e-6),
}


def worker(name: str, steps: int, out: str) -> None:
    import numpy as np

    import kinema as km

    step, final, size = WORKLOADS[name]()
    step()  # untimed: first touch, lazy analyses and factorisations
    walls, cpu = [], time.process_time()
    before = harness.sample_cpu()
    for _ in range(steps):
        t = time.perf_counter()
        step()
        walls.append(time.perf_counter() - t)
    load = harness.other_load(before, harness.sample_cpu())
    cpu = (time.process_time() - cpu) / steps
    np.savez(out, **final())
    print(json.dumps(dict(wall_ms=statistics.median(walls) * 1e3, cpu_ms=cpu * 1e3, other_load=load, size=size,
                          threads=km.get_num_threads(), version=km.__version__, kinema=str(Path(km.__file__).parent))))


def run_once(python: str, name: str, steps: int, threads: int, state: Path, max_load: float, tries: int) -> dict:
    """One worker process; run again (after a quiet moment) while other processes' load was high."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH="")
    best = None
    for _ in range(tries):
        harness.wait_for_quiet(max_load, timeout=10.0)
        out = subprocess.run([python, __file__, "--worker", name, "--steps", str(steps), "--state", str(state)],
                             env=env, capture_output=True, text=True)
        if out.returncode != 0:
            raise RuntimeError(f"{name} with {python} failed:\n{out.stderr[-3000:]}")
        res = json.loads(out.stdout.strip().splitlines()[-1])
        if best is None or res["other_load"] < best["other_load"]:
            best = res
        if res["other_load"] <= max_load:
            break
    best["disturbed"] = best["other_load"] > max_load
    return best


def compare(a_path: Path, b_path: Path) -> tuple:
    """(bitwise equal, largest difference relative to each array's largest magnitude, detail)."""
    import numpy as np

    a, b = np.load(a_path), np.load(b_path)
    if sorted(a.files) != sorted(b.files):
        return False, float("inf"), f"arrays differ: {sorted(a.files)} vs {sorted(b.files)}"
    worst, where = 0.0, ""
    for k in a.files:
        x, y = a[k], b[k]
        if x.shape != y.shape:
            return False, float("inf"), f"{k}: shape {x.shape} vs {y.shape}"
        if np.array_equal(x, y):
            continue
        scale = max(float(np.abs(x).max()), np.finfo(float).tiny)
        rel = float(np.abs(x - y).max()) / scale
        if rel >= worst:
            worst, where = rel, k
    return worst == 0.0, worst, where


FIELDS = ["repeat", "workload", "build", "wall_ms", "cpu_ms", "other_load", "disturbed", "size", "threads",
          "version", "kinema", "result"]


def markdown(rows, header: str) -> str:
    """The table of medians over the repeats, per workload (in the order of the rows)."""
    lines = [header, "",
             "| workload | size | before ms/step (min-max) | after ms/step (min-max) | after / before | "
             "CPU ms/step before / after | CPU after / before | max other load | result |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in dict.fromkeys(x["workload"] for x in rows):
        mine = [x for x in rows if x["workload"] == name]
        wall, cpu = {}, {}
        for build in ("before", "after"):
            w = [float(x["wall_ms"]) for x in mine if x["build"] == build]
            wall[build] = (statistics.median(w), min(w), max(w))
            cpu[build] = statistics.median(float(x["cpu_ms"]) for x in mine if x["build"] == build)
        load = max(float(x["other_load"]) for x in mine)
        b, a = wall["before"], wall["after"]
        lines.append(f"| {name} | {mine[0]['size']} | {b[0]:.2f} ({b[1]:.2f}-{b[2]:.2f}) | "
                     f"{a[0]:.2f} ({a[1]:.2f}-{a[2]:.2f}) | {a[0] / b[0]:.3f} | {cpu['before']:.2f} / {cpu['after']:.2f} | "
                     f"{cpu['after'] / cpu['before']:.3f} | {load:.2f} | {mine[0]['result']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("before", nargs="?", help="python of the environment with the older build")
    ap.add_argument("after", nargs="?", help="python of the environment with the newer build")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=10, help="timed steps per run")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--only", nargs="+", choices=sorted(WORKLOADS), help="a subset of the workloads")
    ap.add_argument("--max-load", type=float, default=0.25, help="other processes' load (cores) that marks a run disturbed")
    ap.add_argument("--tries", type=int, default=2, help="runs of a disturbed (workload, build) before keeping the least loaded")
    ap.add_argument("--out", default=str(HERE / "out" / "shape_compare"), help="OUT.csv and OUT.md are written")
    ap.add_argument("--table", metavar="CSV", help="only print the markdown table of an earlier run's OUT.csv")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--state", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker, args.steps, args.state)
        return 0
    if args.table:
        with open(args.table, newline="") as fh:
            print(markdown(list(csv.DictReader(fh)), f"From {args.table}."), end="")
        return 0
    if not args.before or not args.after:
        ap.error("give the two interpreters, BEFORE_PYTHON and AFTER_PYTHON")
    for label, python in (("before", args.before), ("after", args.after)):
        if not Path(python).exists():
            ap.error(f"{label}: no interpreter at {python}")
    if args.repeats < 1 or args.steps < 1:
        ap.error("--repeats and --steps must be >= 1")
    names = args.only or list(WORKLOADS)
    builds = {"before": args.before, "after": args.after}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows, diffs = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for name in names:
                order = list(builds) if r % 2 == 0 else list(builds)[::-1]
                for build in order:
                    state = Path(tmp) / f"{name}_{build}.npz"
                    res = run_once(builds[build], name, args.steps, args.threads, state, args.max_load, args.tries)
                    rows.append(dict(repeat=r, workload=name, build=build, **res))
                    print(f"repeat {r} {name:17s} {build:6s} {res['wall_ms']:9.2f} ms/step  "
                          f"cpu {res['cpu_ms']:9.2f} ms  other_load {res['other_load']:.2f}"
                          f"{'  DISTURBED' if res['disturbed'] else ''}", flush=True)
                if r == 0:
                    diffs[name] = compare(Path(tmp) / f"{name}_before.npz", Path(tmp) / f"{name}_after.npz")
    for row in rows:
        same, rel, where = diffs[row["workload"]]
        row["result"] = "bitwise" if same else f"differs: {where} {rel:.1e} (relative to max)"
    with open(out.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    header = (f"Steps timed per run: {args.steps}; repeats: {args.repeats}; threads: {args.threads}; "
              f"machine load cap {args.max_load} cores; script at commit {harness.git_commit(HERE)}.")
    table = markdown(rows, header)
    out.with_suffix(".md").write_text(table)
    print("\n" + table)
    print(f"wrote {out.with_suffix('.csv')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
