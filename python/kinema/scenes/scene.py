"""Scene files: load, validate, override and run.

A scene file is TOML with the tables ``[scene]`` (name, duration, fps, metric), ``[solver]``
(``type`` names the solver, the other keys are its options), ``[[objects]]`` (each with a
``type`` the solver knows), ``[output]`` (which files to write) and ``[quick]`` (overrides for a
short test run, in the shape of the file or as dotted key paths). ``kinema list --keys`` lists
every key; the user guide (docs/guide/scenes.md) describes the format.
"""

from __future__ import annotations

import copy
import hashlib
import json
import re
import sys
from pathlib import Path

from kinema.scenes import adapters
from kinema.scenes.render3d import MODES
from kinema.scenes.schema import Bool, Context, Field, Int, ListOf, Real, SceneError, Str, Table, Tagged, Vec

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

SCENE = Table({
    "name": Field(Str()),
    "description": Field(Str(), ""),
    "duration": Field(Real(gt=0), doc="simulated time [s]"),
    "fps": Field(Real(gt=0), 30.0, "frames per simulated second"),
    "metric": Field(Str(), None, "the diagnostic a sweep reports as its error metric"),
    "threads": Field(Int(ge=1, le=4096), None, "OpenMP threads (default: all)"),
})

OUTPUT = Table({
    "png": Field(Bool(), True, "a preview image per frame"),
    "mp4": Field(Bool(), True, "the frames as a video (ffmpeg)"),
    "vtu": Field(Bool(), False, "particles and meshes as VTU (meshio)"),
    "ply": Field(Bool(), False, "particles and surfaces as PLY (meshio)"),
    "vti": Field(Bool(), False, "grids as VTK image data"),
    "every": Field(Int(ge=1), 1, "frames between data files (VTU, PLY, VTI)"),
    "checkpoint_every": Field(Int(ge=1), 1, "frames between checkpoints"),
    "width": Field(Int(ge=16), 640, "image width [pixels]"),
    "height": Field(Int(ge=16), None, "preview/pathtrace image height [pixels] (default 3/4 of the width)"),
    "render": Field(Str(MODES), None, '"flat" (NumPy colour-mapped view), "preview" (km.render\'s z-buffered '
                    'view) or "pathtrace" (km.render\'s path tracer); default "preview" for 3D particle and '
                    'mesh scenes, "flat" otherwise'),
    "spp": Field(Int(ge=1), 16, "pathtrace: samples per pixel"),
    "max_depth": Field(Int(ge=1), 8, "pathtrace: bounces per path"),
    "seed": Field(Int(ge=0), 0, "pathtrace: random seed (the same for every frame)"),
    "camera": Field(Table({
        "look_from": Field(Vec(3), None, "camera position [m]"),
        "look_at": Field(Vec(3), None, "the point in the image centre [m]"),
        "up": Field(Vec(3), None, "the direction shown upwards (default: the view's up axis)"),
        "vfov": Field(Real(gt=0, le=170), None, "vertical field of view [degrees] (default 40)"),
    }), None, "preview/pathtrace camera; missing keys are computed from the scene's bounds"),
    "view": Field(Vec(2, Int(ge=0)), None, "the two world axes the preview shows (right, up)"),
    "field": Field(Str(), None, "what the preview colours (solver-specific)"),
    "range": Field(Vec(2), None, "colour range [lo, hi]"),
    "colormap": Field(Str(), "viridis", "a matplotlib colormap name"),
})

_TOP = ("scene", "solver", "objects", "output", "quick")
_TOKEN = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)|\[(\d+)\]")


def _split(path):
    """'objects[2].region.radius' -> ['objects', 2, 'region', 'radius']."""
    keys = []
    for part in path.split("."):
        tokens = list(_TOKEN.finditer(part))
        if not tokens or "".join(t.group(0) for t in tokens) != part:
            raise ValueError(f"--set: cannot read the key path {path!r} (example: objects[0].region.radius)")
        keys += [t.group(1) if t.group(1) else int(t.group(2)) for t in tokens]
    return keys


def parse_value(text):
    """A TOML value (1e-3, [64, 64], true, "bfecc"); anything else is taken as a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
    except RecursionError:
        raise ValueError(f"the value {text[:40]!r}...: arrays or tables nested too deeply") from None


def apply_override(raw, path, value):
    """Sets the key path in the raw document (creating missing tables)."""
    keys = _split(path)
    node = raw
    for i, key in enumerate(keys[:-1]):
        nxt = keys[i + 1]
        if isinstance(key, int):
            if not isinstance(node, list) or key >= len(node):
                raise ValueError(f"--set {path}: {'.'.join(map(str, keys[:i]))} has no item {key}")
            node = node[key]
        else:
            if not isinstance(node, dict):
                raise ValueError(f"--set {path}: {key} is not inside a table")
            node = node.setdefault(key, [] if isinstance(nxt, int) else {})
    last = keys[-1]
    if isinstance(last, int):
        if not isinstance(node, list) or last >= len(node):
            raise ValueError(f"--set {path}: no item {last} there")
        node[last] = value
    else:
        if not isinstance(node, dict):
            raise ValueError(f"--set {path}: not inside a table")
        node[last] = value


def _flatten(table, prefix=""):
    """A [quick] table as (key path, value) pairs: nested tables recurse, other values are set."""
    for key, value in table.items():
        path = f"{prefix}.{key}" if prefix else key
        if isinstance(value, dict) and _TOKEN.fullmatch(key):
            yield from _flatten(value, path)
        else:
            yield path, value


class Scene:
    """A validated scene: ``Scene.load(path)``, then :meth:`run` (or :meth:`build` for a loop
    of one's own). ``config`` holds the validated tables with every default filled in."""

    def __init__(self, raw, path="<scene>", overrides=(), quick=False):
        self.path = str(path)
        raw = copy.deepcopy(raw)
        self.ctx = Context(self.path)
        for key in raw:
            if key not in _TOP:
                raise self.error(key, f"unknown table (known: {', '.join(_TOP)})")
        quick_table = raw.pop("quick", {})
        if not isinstance(quick_table, dict):
            raise self.error("quick", "expected a table of overrides")
        pairs = list(_flatten(quick_table)) if quick else []
        for path_, value in pairs + [(p, v) for p, v in overrides]:
            apply_override(raw, path_, value)
        self.overrides = [(p, v) for p, v in overrides]
        self.quick = quick
        self.config = self._validate(raw)
        self.name = self.config["scene"]["name"]
        self.solver = self.config["solver"]["type"]

    @classmethod
    def load(cls, path, *, overrides=(), quick=False):
        """Reads and validates a scene file. overrides: (key path, value) pairs applied before
        validation ("solver.resolution", [32, 32]); quick: apply the file's [quick] table."""
        path = Path(path)
        try:
            with open(path, "rb") as fh:
                raw = tomllib.load(fh)
        except FileNotFoundError:
            raise SceneError(path, "", "no such scene file") from None
        except IsADirectoryError:
            raise SceneError(path, "", "is a folder, expected a scene file (.toml)") from None
        except (PermissionError, UnicodeDecodeError) as exc:
            raise SceneError(path, "", f"cannot read it ({exc.__class__.__name__}: {exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(path, "", f"not valid TOML: {exc}") from None
        except RecursionError:
            raise SceneError(path, "", "not usable: arrays or tables nested too deeply") from None
        return cls(raw, path, overrides, quick)

    def error(self, path, message):
        return self.ctx.error(path, message)

    def _validate(self, raw):
        ctx = self.ctx
        solver_raw = raw.get("solver")
        if not isinstance(solver_raw, dict):
            raise self.error("solver", "missing required table (with type = " +
                             " | ".join(f'"{n}"' for n in adapters.ADAPTERS) + ")")
        kind = solver_raw.get("type")
        if kind not in adapters.ADAPTERS:
            expected = ", ".join(f'"{n}"' for n in adapters.ADAPTERS)
            raise self.error("solver.type", f"expected one of {expected}, got {kind!r}")
        self.adapter = adapters.load(kind)
        spec = Table({
            "scene": Field(SCENE),
            "solver": Field(Tagged("type", {kind: self.adapter.SOLVER})),
            "objects": Field(ListOf(Tagged("type", self.adapter.OBJECTS), min_length=1)),
            "output": Field(OUTPUT, {}),
        })
        config = spec.validate(raw, ctx, "")
        if "output" not in raw:
            config["output"] = OUTPUT.validate({}, ctx, "output")
        self.dim = self.adapter.dimension(config["solver"], config["objects"])
        for path, n in ctx.spatial:
            if n != self.dim:
                raise self.error(path, f"expected {self.dim} components (this is a {self.dim}D scene), got {n}")
        view = config["output"]["view"]
        if view is not None and (max(view) >= self.dim or view[0] == view[1]):
            raise self.error("output.view", f"expected two different axes in 0..{self.dim - 1}, got {view}")
        out = config["output"]
        # 3D scenes drawn through km.render: a Geometry per frame, or their own perspective image
        geometric = self.dim == 3 and (hasattr(self.adapter.Simulation, "geometry")
                                       or getattr(self.adapter.Simulation, "PERSPECTIVE", False))
        if out["render"] is None:
            out["render"] = "preview" if geometric else "flat"
        elif out["render"] != "flat" and not geometric:
            raise self.error("output.render", f'"{out["render"]}" draws 3D particles and meshes; a {self.dim}D '
                             f'{kind} scene has only "flat" (its colour-mapped view)')
        _check_colormap(out["colormap"], self.error)
        _check_effort(config, kind, self.error)
        metric = config["scene"]["metric"]
        if metric is not None and metric not in self.adapter.Simulation.DIAGNOSTICS:
            raise self.error("scene.metric", f"expected one of {', '.join(self.adapter.Simulation.DIAGNOSTICS)} "
                             f"for a {kind} scene, got {metric!r}")
        return config

    @property
    def fps(self):
        return self.config["scene"]["fps"]

    @property
    def default_frames(self):
        """Frames of the whole duration: the initial state and one per 1/fps."""
        return int(round(self.config["scene"]["duration"] * self.fps)) + 1

    def fingerprint(self):
        """A hash of everything that shapes the simulation (not the frame count or outputs):
        a checkpoint only resumes the scene that wrote it."""
        sim = {k: self.config[k] for k in ("solver", "objects")}
        sim["fps"] = self.fps
        return hashlib.sha256(json.dumps(sim, sort_keys=True).encode()).hexdigest()[:16]

    def build(self):
        """The solver with exactly the scene's objects (an adapters.base.Simulation)."""
        return self.adapter.Simulation(self)

    def run(self, out, frames=None, *, resume=False, progress=True, on_frame=None):
        """Runs the scene into the folder ``out``: frames 0..frames-1 (frame k at t = k/fps;
        default: the whole duration), writing the outputs the scene asks for and a checkpoint.
        resume: continue from out/checkpoint.npz (bit for bit). progress: a progress bar on
        stderr (True), a stream, or False. on_frame(frame, sim): called after each frame.
        Ctrl-C stops cleanly: the frames written so far stay, the video is made of them, and
        KeyboardInterrupt is raised again. Returns a RunResult."""
        from kinema.scenes.runner import run

        return run(self, out, frames, resume=resume, progress=progress, on_frame=on_frame)

    def __repr__(self):
        return f"Scene({self.name!r}, solver={self.solver!r}, path={self.path!r})"


def examples():
    """The example scenes shipped with kinema: name -> path."""
    folder = Path(__file__).parent / "examples"
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


def resolve(name_or_path):
    """A scene file path, or the name of a shipped example (``kinema list``). A file wins over
    an example of the same name; a folder does not (``kinema run smoke_plume`` runs the
    example even where a folder ``smoke_plume`` exists, e.g. the output of an earlier run)."""
    p = Path(name_or_path)
    if p.is_file() or (p.suffix == ".toml" and not p.is_dir()):
        return p
    known = examples()
    if str(name_or_path) in known:
        return known[str(name_or_path)]
    if p.is_dir():
        raise SceneError(name_or_path, "", "is a folder, expected a scene file (.toml) or an example name "
                         f"(examples: {', '.join(known)})")
    raise SceneError(name_or_path, "", f"no such file, nor an example scene (examples: {', '.join(known)})")


def _check_colormap(name, error):
    import matplotlib

    if name not in matplotlib.colormaps:
        raise error("output.colormap", f"expected a matplotlib colormap name (e.g. viridis, inferno, "
                    f"coolwarm), got {name!r}")


#: refuse runs beyond these: they could not finish (a frame count, a lower bound of solver steps)
MAX_FRAMES = 1_000_000
MAX_STEPS = 1_000_000_000


def _available_memory():
    """Bytes the system can still give (MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _sizes(config, kind):
    """(key path, item count, bytes per item) of what the scene allocates, roughly from above."""
    import math

    solver, objects, out = config["solver"], config["objects"], config["output"]
    width = out["width"]
    height = out["height"] or width * 3 // 4
    sizes = [("output.width, output.height", float(width) * height, 64)]
    if kind == "grid":
        sizes.append(("solver.resolution", math.prod(float(n) for n in solver["resolution"]), 400))
    elif kind == "sph":
        d = len(solver["domain"]["lower"])
        for k, obj in enumerate(objects):
            r = obj["region"]
            if r["shape"] == "box":
                volume = math.prod(max(hi - lo, 0.0) for lo, hi in zip(r["lower"], r["upper"]))
            else:
                volume = (2 * r["radius"]) ** d
            sizes.append((f"objects[{k}].region, solver.spacing", volume / solver["spacing"] ** d, 4000))
        lo, hi = solver["domain"]["lower"], solver["domain"]["upper"]
        area = sum(math.prod(max(h - l, 0.0) for a, (l, h) in enumerate(zip(lo, hi)) if a != skip)
                   for skip in range(d))
        sizes.append(("solver.domain, solver.spacing", 4 * area / solver["spacing"] ** (d - 1), 4000))
    elif kind in ("massspring", "fem"):
        for k, obj in enumerate(objects):
            for key in ("resolution", "cells"):
                if key in obj:
                    sizes.append((f"objects[{k}].{key}", math.prod(float(n) + 1 for n in obj[key]), 3000))
    elif kind == "vortex":
        for k, obj in enumerate(objects):
            if "particles" in obj:
                sizes.append((f"objects[{k}].particles", float(obj["particles"]), 2000))
    return sizes


def min_steps(config, frames):
    """A lower bound of the solver steps of ``frames`` frames, and the key that sets it."""
    solver, fps = config["solver"], config["scene"]["fps"]
    steps, why = float(frames), "scene.fps"
    if "substeps" in solver:
        steps, why = frames * float(solver["substeps"]), "solver.substeps"
    if "max_dt" in solver:
        # The grid's adaptive step is at most max_dt (and at least one step per frame).
        steps, why = max(float(frames), frames / fps / solver["max_dt"]), "solver.max_dt"
    return steps, why


def _check_effort(config, kind, error):
    """Refuses scenes that cannot finish (too many frames or solver steps) or cannot fit in
    memory, naming the keys, before anything is built or written."""
    scene, solver = config["scene"], config["solver"]
    frames = scene["duration"] * scene["fps"]
    if not frames <= MAX_FRAMES:
        raise error("scene.duration", f"{scene['duration']:g} s at scene.fps = {scene['fps']:g} is {frames:.3g} "
                    f"frames, more than {MAX_FRAMES:,} (shorten the duration or lower the fps)")
    steps, why = min_steps(config, frames)
    if not steps <= MAX_STEPS:
        raise error(why, f"the run would take at least {steps:.3g} solver steps (scene.duration = "
                    f"{scene['duration']:g} s), more than {MAX_STEPS:,}")
    available = _available_memory()
    if available is None:
        return
    for key, count, per_item in _sizes(config, kind):
        need = count * per_item
        if not need <= available:
            raise error(key, f"about {count:.3g} items needing about {need / 2**30:.3g} GiB, more than the "
                        f"{available / 2**30:.3g} GiB of memory available")
