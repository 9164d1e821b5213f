"""Parameter sweeps of a scene on Dask: every combination of the given values is one run
(a scene with those overrides), run on a local cluster or on a scheduler's workers, gathered
into sweep.csv (one row per run) and sweep.png (wall time and metric against the parameter).
"""

from __future__ import annotations

import csv
import itertools
import shutil
import time
from pathlib import Path

from kinema.scenes.output import atomic_path
from kinema.scenes.scene import Scene, parse_value

MAX_WORKERS = 256


def parse_param(text):
    """'solver.dt=1e-3,5e-4' -> ('solver.dt', [0.001, 0.0005]). A bare key (no dot, no
    index) is kept as given; :func:`resolve_key` finds it in the scene."""
    key, sep, values = text.partition("=")
    if not sep or not key or not values:
        raise ValueError(f"--param: expected KEY=V1,V2,..., got {text!r}")
    key = key.strip()
    # Split on commas outside brackets, so that [32, 32],[64, 64] gives two vectors.
    parts, depth, cur = [], 0, ""
    for ch in values:
        depth += ch == "["
        depth -= ch == "]"
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    return key, [parse_value(p.strip()) for p in parts]


def resolve_key(path, key, quick=False):
    """The key path a bare ``--param`` key names: ``solver.KEY`` when the solver has that
    option, else ``objects[i].KEY`` when exactly one object of the scene has it (e.g.
    ``youngs_modulus`` of the only fem body). A dotted or indexed path is returned as given."""
    if "." in key or "[" in key:
        return key
    scene = Scene.load(path, quick=quick)
    if key in scene.adapter.SOLVER.fields:
        return f"solver.{key}"
    hits = [f"objects[{i}].{key}" for i, obj in enumerate(scene.config["objects"])
            if key in scene.adapter.OBJECTS[obj["type"]].fields]
    if len(hits) == 1:
        return hits[0]
    if hits:
        raise ValueError(f"--param {key}: several objects have it ({', '.join(hits)}); give the full key path")
    raise ValueError(f"--param {key}: neither a {scene.solver} solver option nor a key of the scene's objects "
                     f"(solver options: {', '.join(sorted(scene.adapter.SOLVER.fields))}; "
                     "kinema list --keys shows all)")


def run_one(path, overrides, quick, frames, out):
    """One run of the sweep (executed on a Dask worker): a result row."""
    # The adapters import these on first use; a worker's first run would be timed with them.
    import matplotlib.colors  # noqa: F401
    import scipy.spatial  # noqa: F401

    scene = Scene.load(path, overrides=overrides, quick=quick)
    t0 = time.perf_counter()
    result = scene.run(out, frames, progress=False)
    row = {key: value for key, value in overrides}
    row.update(wall_seconds=time.perf_counter() - t0, steps=result.steps, frames=result.frames,
               sim_time=result.time)
    metric = scene.config["scene"]["metric"]
    row["metric"] = result.diagnostics.get(metric) if metric else None
    row.update(result.diagnostics)
    return row


def sweep(path, params, out, *, frames=None, quick=False, overrides=(), scheduler=None, workers=2,
          processes=True, log=print):
    """Runs every combination of ``params`` ({key path: [values]}; a bare key as in
    :func:`resolve_key`) and writes out/sweep.csv and out/sweep.png. scheduler: a Dask scheduler address (default: a LocalCluster of
    ``workers`` workers, separate processes unless processes=False). Returns the rows."""
    if not params:
        raise ValueError("params: expected at least one --param KEY=V1,V2")
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise ValueError(f"workers: expected an integer in 1..{MAX_WORKERS}, got {workers!r}")
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise ImportError("kinema sweep needs Dask: pip install 'kinema[sweep]' "
                          "(or pip install 'dask[distributed]')") from None
    params = {resolve_key(path, k, quick): v for k, v in params.items()}
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} is a file, expected a folder")
    keys = list(params)
    combos = list(itertools.product(*(params[k] for k in keys)))
    # Validate every combination here, so that a bad value fails before any cluster starts.
    for combo in combos:
        scene = Scene.load(path, overrides=list(overrides) + list(zip(keys, combo)), quick=quick)
    metric = scene.config["scene"]["metric"]
    out.mkdir(parents=True, exist_ok=True)
    # Runs of an earlier, larger sweep into this folder would be mistaken for this one's.
    for folder in out.glob("run_[0-9][0-9][0-9]"):
        if int(folder.name[4:]) >= len(combos) and (folder / "run.json").is_file():
            shutil.rmtree(folder)
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        log(f"sweep: {len(combos)} runs on {scheduler or f'a local cluster of {workers} workers'}")
        futures = [client.submit(run_one, str(path), list(overrides) + list(zip(keys, combo)), quick, frames,
                                 str(out / f"run_{i:03d}"), pure=False)
                   for i, combo in enumerate(combos)]
        rows = client.gather(futures)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    for row in rows:  # the swept keys alone, without the fixed overrides
        for key, _ in overrides:
            if key not in keys:
                row.pop(key, None)
    _write_csv(out / "sweep.csv", rows)
    _plot(out / "sweep.png", rows, keys, metric)
    log(f"sweep: wrote {out / 'sweep.csv'} and {out / 'sweep.png'}")
    return rows


def _write_csv(path, rows):
    names = []
    for row in rows:
        names += [k for k in row if k not in names]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=names)
        writer.writeheader()
        writer.writerows(rows)


def _plot(path, rows, keys, metric=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = keys[0]
    numeric = all(isinstance(r[key], (int, float)) and not isinstance(r[key], bool) for r in rows)
    xs = [r[key] if numeric else str(r[key]) for r in rows]
    has_metric = any(r["metric"] is not None for r in rows)
    fig, axes = plt.subplots(1, 2 if has_metric else 1, figsize=(9 if has_metric else 5, 3.8), squeeze=False)
    ax = axes[0, 0]
    ax.plot(xs, [r["wall_seconds"] for r in rows], "o")
    ax.set_xlabel(key)
    ax.set_ylabel("wall time [s]")
    if has_metric:
        ax2 = axes[0, 1]
        ax2.plot([r["wall_seconds"] for r in rows], [r["metric"] for r in rows], "o")
        for r in rows:
            label = ", ".join(f"{k.rsplit('.', 1)[-1]}={r[k]}" for k in keys)
            ax2.annotate(label, (r["wall_seconds"], r["metric"]), fontsize=7)
        ax2.set_xlabel("wall time [s]")
        ax2.set_ylabel(metric or "metric")
    if numeric and all(x > 0 for x in xs):
        ax.set_xscale("log")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
