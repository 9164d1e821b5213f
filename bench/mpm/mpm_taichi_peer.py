"""Taichi peer of bench/mpm/mpm_bench.py: Taichi's own shipped MPM examples (mpm88: 2D weakly
compressible fluid; mpm128: water, jelly and snow with SVD plasticity; mpm3d: 3D fluid), run as
they ship in the installed taichi package (taichi/examples/simulation/<kind>.py), headless on the
CPU backend. Nothing of them is copied here: the example's file is read from the package at run
time, its `ti.init(arch=ti.gpu)` becomes a CPU init with the thread count asked for, and its GUI
loop (the lines from the GUI window on) is left out; `substep` is then called directly. Float
type as shipped (`float` = Taichi's default f32). Run in its own process by mpm_bench.py:

    .venv/bin/python bench/mpm/mpm_taichi_peer.py {mpm88,mpm128,mpm3d} STEPS START.npz [--threads T]

Writes the initial state the example's own init()/reset() made (x, v, n_grid, dt, and for
mpm128 the material ids and gravity) to START.npz, so that kinema starts from it; prints one
JSON line: seconds per substep, wall and CPU (best of 3 blocks of STEPS substeps, after a
warm-up block that compiles the kernels) and the mean particle position afterwards (the bench
checks it against kinema's run from the same start).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
import taichi as ti

# Where each example's GUI part starts (everything from this line on is left out) and the names
# of its state: positions, velocities, the init function.
EXAMPLES = {
    "mpm88": dict(cut=r"^init\(\)\s*$", x="x", v="v", init="init"),
    "mpm128": dict(cut=r"^print\(\"\[Hint\]", x="x", v="v", init="reset"),
    "mpm3d": dict(cut=None, x="F_x", v="F_v", init="init"),  # its GUI is in main()
}


def load_example(kind, threads):
    path = Path(ti.__file__).resolve().parent / "examples" / "simulation" / f"{kind}.py"
    source = path.read_text()
    spec = EXAMPLES[kind]
    if spec["cut"]:
        match = re.search(spec["cut"], source, flags=re.M)
        if match is None:
            raise SystemExit(f"{path}: the GUI part ({spec['cut']}) was not found; the example changed")
        source = source[:match.start()]
    init = "ti.init(arch=ti.gpu)"
    if init not in source:
        raise SystemExit(f"{path}: `{init}` not found; the example changed")
    source = source.replace(init, f"ti.init(arch=ti.cpu, cpu_max_num_threads={threads}, random_seed=0, "
                                  "offline_cache=True)")
    module = {"__name__": f"{kind}_headless", "__file__": str(path)}
    exec(compile(source, str(path), "exec"), module)
    module[spec["init"]]()
    if kind == "mpm128":
        module["gravity"][None] = [0, -1]  # as the example sets it before its loop
    return module, spec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("kind", choices=sorted(EXAMPLES))
    ap.add_argument("steps", type=int)
    ap.add_argument("start")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    mod, spec = load_example(a.kind, a.threads)
    x, v, substep = mod[spec["x"]], mod[spec["v"]], mod["substep"]
    start = dict(x=x.to_numpy().astype(np.float64), v=v.to_numpy().astype(np.float64),
                 n_grid=mod["n_grid"], dt=mod["dt"])
    if a.kind == "mpm128":
        start["material"] = mod["material"].to_numpy()
        start["gravity"] = mod["gravity"].to_numpy() * 30  # the example's grid update scales it by 30
    np.savez(a.start, **start)
    for _ in range(a.steps):  # warm-up: JIT compilation
        substep()
    ti.sync()
    best, best_cpu = float("inf"), float("inf")
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(a.steps):
            substep()
        ti.sync()
        best = min(best, (time.perf_counter() - t0) / a.steps)
        best_cpu = min(best_cpu, (time.process_time() - c0) / a.steps)
    xs = x.to_numpy()
    print(json.dumps({"seconds": best, "cpu_seconds": best_cpu, "mean": xs.mean(axis=0).tolist(),
                      "finite": bool(np.isfinite(xs).all()), "total_steps": 4 * a.steps,
                      "taichi": ti.__version__, "file": f"taichi/examples/simulation/{a.kind}.py"}))


if __name__ == "__main__":
    main()
