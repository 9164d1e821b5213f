"""Times SPlisHSPlasH (pysplishsplash) on kinema's 3D dam break; run as a subprocess by
bench/sph/sph_bench.py, so that a crash of the peer cannot take the benchmark down.

    python bench/sph/splishsplash_run.py --method wcsph --spacing S --steps N --dt DT --tol TOL \\
        --stiffness B --out OUT.json [--skip K] [--boundary akinci|volume-map] [--cache DIR]

K steps are run untimed first (the benchmark's start-up transient), then, after waiting up to
--quiet-timeout seconds for a quiet machine, N are timed, each stamped with wall and process CPU
time by a per-step callback; other_load is harness.other_load over the timed steps.

Scene (the same as sph_bench.scene): water column [0, a] x [0, 2a] x [0, a] (a = 0.5 m) in the
closed box [0, 4a] x [0, 3a] x [0, a], no viscosity, fixed dt (CFL off). The fluid starts on
kinema's lattice exactly (first point at spacing/2 from each wall; checked after loading, the
run stops if SPlisHSPlasH placed it elsewhere). The walls are SPlisHSPlasH's own boundary
models, placed so that a particle of that lattice next to a wall is at rest density:

* ``akinci`` (Akinci et al. 2012, as kinema): one layer of samples on the box surface, regular
  triangle sampling. SPlisHSPlasH normalises a one-layer wall to act like a full particle layer
  (Akinci's volume correction), so samples on the wall plane put the first fluid layer (at
  spacing/2) at 1.5 rho0 and WCSPH explodes. The sampled box is therefore grown by spacing/2 on
  every side, which puts the samples where kinema's first layer of wall samples sits.
* ``volume-map`` (Bender et al. 2019, the method of SPlisHSPlasH's own scenes, e.g.
  data/Scenes/DamBreakModel.json): an SDF-based volume map, precomputed once (its time is the
  "precompute" entry) and cached in --cache. Its effective wall lies about a particle radius
  inside the surface: grown by spacing/2 it put the particles along the box's edges at 2.1 rho0
  (WCSPH blows up), grown by a spacing the first layer starts slightly below rest density (it
  settles onto the wall during the start-up), which is what this option uses.

The import needs the system's libGLdispatch.so.0 loaded first with RTLD_GLOBAL; the run goes
through runSimulation() with a per-step callback that ends the process after the last timed
step (setting STOP_AT from the callback does not stop a headless run). The solver parameters are
set on the time step object and read back (pysplishsplash 2.19 reads none of them from a flat
scene file): they go to the output JSON with the rest of the configuration.
"""

import argparse
import ctypes
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

A = 0.5
BOX = (4 * A, 3 * A, A)
COLUMN = (A, 2 * A, A)
METHODS = {"wcsph": 0, "dfsph": 4}
BOUNDARIES = {"akinci": 0, "volume-map": 2}
GROW = {"akinci": 0.5, "volume-map": 1.0}  # box grown by this many spacings on each side


def lattice_count(extent, spacing):
    """Points per axis of km.sph.block: every s/2 + k s that lies in [0, extent]."""
    return int(extent / spacing + 0.5)


def scene(method, spacing, dt, boundary, models):
    grow = GROW[boundary] * spacing
    counts = [lattice_count(e, spacing) for e in COLUMN]
    body = {
        "geometryFile": os.path.join(models, "UnitBox.obj"),
        "translation": [e / 2 for e in BOX], "scale": [e + 2 * grow for e in BOX],
        "isDynamic": False, "isWall": True, "mapInvert": True,
    }
    if boundary == "akinci":
        body["samplingMode"] = 1  # regular triangle sampling: fewer, evener samples than Poisson
    else:
        # Its default map resolution (20^3). One cell per support radius, as DamBreakModel.json
        # has, made WCSPH blow up from the box's edges (measured at 9,826 particles).
        body["mapThickness"] = 0.0
    return {
        "Configuration": {
            "particleRadius": spacing / 2,
            "simulationMethod": METHODS[method],
            "gravitation": [0, -9.81, 0],
            "timeStepSize": dt,
            "cflMethod": 0,
            "stopAt": 1000.0,
            "enableZSort": True,
            "boundaryHandlingMethod": BOUNDARIES[boundary],
        },
        "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 0}],
        "RigidBodies": [body],
        # A dense-mode-0 block puts its first point one spacing (2 r) past `start` and fills
        # round((end - start) / spacing) - 1 points per axis: this gives kinema's lattice.
        "FluidBlocks": [{"denseMode": 0, "start": [-spacing / 2] * 3,
                         "end": [-spacing / 2 + (c + 1) * spacing for c in counts]}],
    }


def check_lattice(fluid, spacing):
    """Stop unless the loaded fluid is kinema's lattice (same count, same corner points)."""
    counts = [lattice_count(e, spacing) for e in COLUMN]
    n = fluid.numActiveParticles()
    lo, hi = [float("inf")] * 3, [-float("inf")] * 3
    for i in range(n):
        p = fluid.getPosition(i)
        lo = [min(a, b) for a, b in zip(lo, p)]
        hi = [max(a, b) for a, b in zip(hi, p)]
    want_hi = [spacing / 2 + (c - 1) * spacing for c in counts]
    off = max(max(abs(a - spacing / 2) for a in lo), max(abs(a - b) for a, b in zip(hi, want_hi)))
    if n != counts[0] * counts[1] * counts[2] or off > 1e-4 * spacing + 1e-6:
        sys.exit(f"fluid not on kinema's lattice: {n} particles in {lo}..{hi}, "
                 f"want {counts} points from {spacing / 2} to {want_hi}")


def apply_solver(ts, method, tol, stiffness):
    """Sets the solver parameters on the time step object and returns them read back."""
    if method == "wcsph":
        ts.setValueFloat(ts.STIFFNESS, stiffness)
        ts.setValueFloat(ts.EXPONENT, 7.0)
        return {"stiffness": ts.getValueFloat(ts.STIFFNESS), "exponent": ts.getValueFloat(ts.EXPONENT)}
    ts.setValueFloat(ts.MAX_ERROR, 100 * tol)  # in percent
    ts.setValueFloat(ts.MAX_ERROR_V, 100 * tol)
    ts.setValueInt(ts.MAX_ITERATIONS, 100)
    ts.setValueInt(ts.MAX_ITERATIONS_V, 100)
    ts.setValueInt(ts.MIN_ITERATIONS, 2)
    return {"maxError_percent": ts.getValueFloat(ts.MAX_ERROR),
            "maxErrorV_percent": ts.getValueFloat(ts.MAX_ERROR_V),
            "maxIterations": ts.getValueInt(ts.MAX_ITERATIONS),
            "minIterations": ts.getValueInt(ts.MIN_ITERATIONS),
            "divergenceSolver": ts.getValueBool(ts.USE_DIVERGENCE_SOLVER)}


def state_check(fluid, spacing):
    """Mean compression (as kinema's density_error), particles out of the box, top speed."""
    n = fluid.numActiveParticles()
    comp = out = 0
    vmax = 0.0
    for i in range(n):
        comp += max(fluid.getDensity(i) / 1000.0 - 1.0, 0.0)
        p = fluid.getPosition(i)
        out += any(not (-spacing <= x <= e + spacing) for x, e in zip(p, BOX))
        v = fluid.getVelocity(i)
        vmax = max(vmax, (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) ** 0.5)
    return {"density_error": comp / n, "outside_box": out, "max_speed": vmax}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--method", choices=sorted(METHODS), required=True)
    p.add_argument("--spacing", type=float, required=True)
    p.add_argument("--steps", type=int, required=True, help="timed steps")
    p.add_argument("--dt", type=float, required=True)
    p.add_argument("--tol", type=float, default=1e-3, help="DFSPH density tolerance (mean compression)")
    p.add_argument("--stiffness", type=float, default=0.0, help="WCSPH Tait B [Pa]")
    p.add_argument("--out", required=True)
    p.add_argument("--skip", type=int, default=0, help="untimed start-up steps")
    p.add_argument("--boundary", choices=sorted(BOUNDARIES), default="akinci")
    p.add_argument("--quiet-timeout", type=float, default=harness.DEFAULT_QUIET_TIMEOUT,
                   help="seconds to wait for a quiet machine before the timed steps")
    p.add_argument("--cache", help="directory kept between runs for the wall sampling / volume map")
    args = p.parse_args()
    if args.method == "wcsph" and args.stiffness <= 0:
        p.error("--stiffness: WCSPH needs kinema's Tait B > 0")

    ctypes.CDLL("libGLdispatch.so.0", mode=ctypes.RTLD_GLOBAL)
    import pysplishsplash as sph

    models = os.path.join(os.path.dirname(sys.executable), "data", "models")
    work = args.cache or tempfile.mkdtemp(prefix="splish_")
    os.makedirs(work, exist_ok=True)
    path = os.path.join(work, f"scene_{args.method}_{args.boundary}.json")
    with open(path, "w") as f:
        json.dump(scene(args.method, args.spacing, args.dt, args.boundary, models), f)
    cache_dir = os.path.join(work, "Cache")
    cached = sorted(os.listdir(cache_dir)) if os.path.isdir(cache_dir) else []
    t_start, c_start = time.perf_counter(), time.process_time()
    base = sph.Exec.SimulatorBase()
    base.init(useGui=False, outputDir=work, sceneFile=path)
    sim = sph.Simulation.getCurrent()
    tm = sph.TimeManager.getCurrent()
    stamps = []  # (wall, cpu, simulated time, solver iterations) after each step
    load = []  # harness CPU samples at the start and the end of the timed steps
    ts = None

    def finish():
        fluid = sim.getFluidModel(0)
        timed = stamps[args.skip:]
        pairs = list(zip(timed[:-1], timed[1:]))
        bm = sim.getBoundaryModel(0)
        load.append(harness.sample_cpu())
        res = {
            "particles": fluid.numActiveParticles(),
            "other_load": harness.other_load(load[0], load[-1]) if len(load) == 2 else None,
            "per_step": [b[0] - a[0] for a, b in pairs],
            "cpu_per_step": [b[1] - a[1] for a, b in pairs],
            "iterations_per_step": [b[3] for a, b in pairs],
            "sim_dt_per_step": [b[2] - a[2] for a, b in pairs],
            "precompute_s": stamps[0][0] - t_start if stamps else None,
            "precompute_cpu_s": stamps[0][1] - c_start if stamps else None,
            "boundary": args.boundary,
            # Nothing new in the cache: the wall sampling / volume map was read, not computed.
            "precompute_cached": set(os.listdir(cache_dir)) <= set(cached),
            "boundary_samples": bm.numberOfParticles() if hasattr(bm, "numberOfParticles") else 0,
            "applied": {**applied, **config},
            **state_check(fluid, args.spacing),
        }
        text = json.dumps(res, default=float)  # its getters return numpy float32
        with open(args.out, "w") as f:
            f.write(text)
        # runSimulation() has no stop from a callback that works headless: leave the process.
        sys.stdout.flush()
        os._exit(0)

    def on_step():
        its = 0
        if args.method == "dfsph":
            its = ts.getValueInt(ts.SOLVER_ITERATIONS) + ts.getValueInt(ts.SOLVER_ITERATIONS_V)
        stamps.append((time.perf_counter(), time.process_time(), tm.getTime(), its))
        if len(stamps) == args.skip + 1:
            # As harness.measure does for kinema: wait (up to --quiet-timeout) for a quiet
            # machine before the timed steps, then restart their clock.
            harness.wait_for_quiet(timeout=args.quiet_timeout)
            load.append(harness.sample_cpu())
            stamps[-1] = (time.perf_counter(), time.process_time(), tm.getTime(), its)
        if len(stamps) > args.skip + args.steps:
            finish()

    base.setTimeStepCB(on_step)
    base.initSimulation()
    check_lattice(sim.getFluidModel(0), args.spacing)
    ts = sim.getTimeStep()
    applied = apply_solver(ts, args.method, args.tol, args.stiffness)
    config = {
        "simulationMethod": sim.getValueInt(sim.SIMULATION_METHOD),
        "boundaryHandlingMethod": sim.getValueInt(sim.BOUNDARY_HANDLING_METHOD),
        "cflMethod": sim.getValueInt(sim.CFL_METHOD),
        "timeStepSize": tm.getTimeStepSize(),
        "zSort": sim.zSortEnabled(),
        "supportRadius": sim.getSupportRadius(),
        "omp_threads": os.environ.get("OMP_NUM_THREADS", "default"),
    }
    base.runSimulation()
    finish()


if __name__ == "__main__":
    main()
