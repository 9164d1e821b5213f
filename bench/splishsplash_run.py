"""Times SPlisHSPlasH (pysplishsplash) on kinema's 3D dam break; run as a subprocess by
bench/sph_bench.py, so that a crash of the peer cannot take the benchmark down.

    python bench/splishsplash_run.py METHOD SPACING STEPS DT TOL STIFFNESS OUT.json [SKIP]

SKIP steps are run untimed first (the benchmark's start-up transient), then STEPS are timed.

The scene mirrors sph_bench.scene(): column [0, a] x [0, 2a] x [0, a] in the box
[0, 4a] x [0, 3a] x [0, a] (a = 0.5 m), particle radius spacing/2, Akinci et al. 2012 boundary
samples (boundaryHandlingMethod 0), no viscosity, fixed dt (CFL off). Its fluid block starts
one spacing (not half) from the walls, and its one-layer Akinci wall sampling over-counts the
density of the wall-adjacent particles: 4.7% mean compression at rest (3,600 particles); the
benchmark's 0.02 s of untimed start-up lets WCSPH push them off (0.96% after 80 steps). The import needs the
system's libGLdispatch.so.0 loaded first with RTLD_GLOBAL; the run goes through runSimulation()
with a per-step callback that records wall times and ends the process after STEPS steps
(setting STOP_AT from the callback does not stop a headless run).
"""

import ctypes
import json
import os
import sys
import tempfile
import time

A = 0.5
METHODS = {"wcsph": 0, "dfsph": 4}


def scene(method, spacing, dt, tol, stiffness, models):
    return {
        "Configuration": {
            "particleRadius": spacing / 2,
            "simulationMethod": METHODS[method],
            "gravitation": [0, -9.81, 0],
            "timeStepSize": dt,
            "cflMethod": 0,
            "stopAt": 100.0,
            "enableZSort": True,
            "boundaryHandlingMethod": 0,
        },
        "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 0}],
        "RigidBodies": [{
            "geometryFile": os.path.join(models, "UnitBox.obj"),
            "translation": [2 * A, 1.5 * A, 0.5 * A], "scale": [4 * A, 3 * A, A],
            "isDynamic": False, "isWall": True, "mapInvert": True,
            "samplingMode": 0,
        }],
        # SPlisHSPlasH fills [start + r, end - r]; half a spacing more gives kinema's lattice count.
        "FluidBlocks": [{"denseMode": 0, "start": [0, 0, 0],
                         "end": [A + spacing / 2, 2 * A + spacing / 2, A + spacing / 2]}],
    }


def main():
    method, spacing, steps, dt, tol, stiffness, out = sys.argv[1:8]
    spacing, steps, dt, tol, stiffness = float(spacing), int(steps), float(dt), float(tol), float(stiffness)
    skip = int(sys.argv[8]) if len(sys.argv) > 8 else 0
    ctypes.CDLL("libGLdispatch.so.0", mode=ctypes.RTLD_GLOBAL)
    import pysplishsplash as sph

    models = os.path.join(os.path.dirname(sys.executable), "data", "models")
    work = tempfile.mkdtemp(prefix="splish_")
    path = os.path.join(work, "scene.json")
    with open(path, "w") as f:
        json.dump(scene(method, spacing, dt, tol, stiffness, models), f)
    base = sph.Exec.SimulatorBase()
    base.init(useGui=False, outputDir=work, sceneFile=path)
    stamps = []

    def finish():
        fluid = sph.Simulation.getCurrent().getFluidModel(0)
        n = fluid.numActiveParticles()
        rho = [fluid.getDensity(i) for i in range(0, n, max(1, n // 20000))]
        err = sum(max(r / 1000 - 1, 0) for r in rho) / len(rho)
        timed = stamps[skip:]
        per_step = [t1 - t0 for t0, t1 in zip(timed[:-1], timed[1:])]
        with open(out, "w") as f:
            json.dump({"particles": n, "per_step": per_step, "density_error": err, "applied": applied}, f)
        # runSimulation() has no stop from a callback that works headless: leave the process.
        sys.stdout.flush()
        os._exit(0)

    def on_step():
        stamps.append(time.perf_counter())
        if len(stamps) > skip + steps:
            finish()

    base.setTimeStepCB(on_step)
    base.initSimulation()
    # The solver parameters are set on the time step object: pysplishsplash 2.19 reads none of
    # them from the scene file (checked by reading them back: with "stiffness" in the
    # Configuration or Materials block WCSPH kept its default of 50 Pa, and DFSPH its maxError
    # 0.01 %, which is why the first driver's WCSPH compressed by 6.4%).
    ts = sph.Simulation.getCurrent().getTimeStep()
    if method == "wcsph":
        ts.setValueFloat(ts.STIFFNESS, stiffness)
        ts.setValueFloat(ts.EXPONENT, 7.0)
        applied = {"stiffness": ts.getValueFloat(ts.STIFFNESS)}
    else:
        ts.setValueFloat(ts.MAX_ERROR, 100 * tol)  # in percent
        ts.setValueFloat(ts.MAX_ERROR_V, 100 * tol)
        ts.setValueInt(ts.MAX_ITERATIONS, 100)
        ts.setValueInt(ts.MAX_ITERATIONS_V, 100)
        ts.setValueInt(ts.MIN_ITERATIONS, 2)
        applied = {"maxError_percent": ts.getValueFloat(ts.MAX_ERROR),
                   "maxErrorV_percent": ts.getValueFloat(ts.MAX_ERROR_V)}
    base.runSimulation()
    finish()


if __name__ == "__main__":
    main()
