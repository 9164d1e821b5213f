"""The fuzz harness of the `kinema` command: malformed scenes, absurd values, damaged
checkpoints, unusable paths, full and read-only disks. Every case must end either in success or
in one line ``kinema...: ...`` naming the key or path at fault, with exit status 2 (1 for a
failing simulation), never a traceback, a crash or a hang; a failed resume leaves the folder as
it was. Each case's outcome is classified and the outcomes are counted.

By default every case runs in this process through ``kinema.cli.main`` (fast); the slow run
repeats them as separate processes of the command (which also catches crashes and hangs).
``python tests/test_cli_fuzz.py [--python PY]`` runs all cases as processes and prints the
counts by outcome (``--python`` picks the interpreter whose kinema is tested).
"""

from __future__ import annotations

import collections
import errno
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from scene_toml import cloth, fem_box

OUTCOMES = ("ok", "error", "traceback", "multi-line", "crash", "hang", "wrong")

QUICK = ["--quick", "--frames", "2", "--set", "output.mp4=false", "--no-progress"]

GOOD = """
[scene]
name = "fuzz"
duration = 0.1
fps = 20
[solver]
type = "vortex"
substeps = 1
[[objects]]
type = "sheet"
center = [0.0, 0.0]
particles = 16
[output]
width = 32
"""


@dataclass
class Case:
    name: str
    argv: list                   # "{tmp}" is replaced by the case's folder
    expect: str = "error"        # "ok" or "error"
    needle: str = ""             # the error line must contain it ("{tmp}" replaced)
    files: dict = field(default_factory=dict)   # relative path -> text or bytes to create
    run_first: bool = False      # tmp/out holds a finished 2-frame run of scene.toml
    damage: object = None        # callable(checkpoint path) applied after run_first
    untouched: bool = False      # the out folder must be unchanged by the command
    patch: object = None         # callable(monkeypatch): in-process only (a full disk, ...)
    cwd_tmp: bool = False        # run with tmp as the working directory


def _scene(**edits):
    text = GOOD
    for old, new in edits.items():
        text = text.replace(old, new)
    return text


def _truncate(p):
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _flip(p):
    data = bytearray(p.read_bytes())
    for k in range(40, len(data), 97):
        data[k] ^= 0xFF
    p.write_bytes(bytes(data))


def _rewrite(meta=None, drop=(), state=None):
    def damage(p):
        import json

        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        m = json.loads(str(arrays["meta"]))
        if meta is not None:
            m.update(meta)
            m = {k: v for k, v in m.items() if v is not _DROP}
        arrays["meta"] = np.array(json.dumps(m))
        for k in drop:
            arrays.pop(k, None)
        arrays.update(state or {})
        np.savez(p, **arrays)
    return damage


_DROP = object()


def _enospc(monkeypatch):
    import kinema.scenes.runner as runner

    def full(path, rgb):
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(path).parent / f".{Path(path).name}.x1.tmp"))
    monkeypatch.setattr(runner.io_out, "write_png", full)


def _read_only(monkeypatch):
    import tempfile as tf

    def denied(*a, dir=None, **k):
        raise PermissionError(errno.EACCES, "Permission denied", str(dir))
    monkeypatch.setattr(tf, "mkstemp", denied)


def _bad_alloc(monkeypatch):
    from kinema.scenes.adapters import base

    def no_memory(self, *a, **k):
        raise MemoryError("std::bad_alloc")
    monkeypatch.setattr(base.Simulation, "__init__", no_memory)


# resume the finished 2-frame run in tmp/out to 4 frames
RESUME = ["run", "{tmp}/scene.toml", "--out", "{tmp}/out", "--resume", "--frames", "4", "--quick", "--no-progress"]
DEEP = "a = " + "[" * 50000 + "]" * 50000 + "\n"
CASES = [
    # -- the command line itself
    Case("no-arguments", [], needle="kinema: the following arguments are required"),
    Case("unknown-command", ["fly"], needle="invalid choice"),
    Case("threads-0", ["run", "{tmp}/scene.toml", "--threads", "0"], needle="--threads: expected an integer",
         files={"scene.toml": GOOD}),
    Case("threads-negative", ["run", "{tmp}/scene.toml", "--threads", "-3"], needle="--threads",
         files={"scene.toml": GOOD}),
    Case("threads-huge", ["run", "{tmp}/scene.toml", "--threads", "100000"], needle="--threads",
         files={"scene.toml": GOOD}),
    Case("scene-threads-huge", ["run", "{tmp}/scene.toml"], needle="scene.threads: expected an integer >= 1 and <= 4096",
         files={"scene.toml": _scene(**{"fps = 20": "fps = 20\nthreads = 100000"})}),
    Case("threads-text", ["run", "{tmp}/scene.toml", "--threads", "many"], needle="--threads",
         files={"scene.toml": GOOD}),
    Case("frames-0", ["run", "{tmp}/scene.toml", "--frames", "0"], needle="--frames", files={"scene.toml": GOOD}),
    Case("frames-huge", ["run", "{tmp}/scene.toml", "--frames", str(2**40)], needle="--frames",
         files={"scene.toml": GOOD}),
    Case("set-without-value", ["run", "{tmp}/scene.toml", "--set", "solver.substeps"], needle="--set expects KEY=VALUE",
         files={"scene.toml": GOOD}),
    Case("set-bad-path", ["run", "{tmp}/scene.toml", "--set", "objects[x=1"], needle="--set",
         files={"scene.toml": GOOD}),
    Case("set-deep-value", ["run", "{tmp}/scene.toml", "--set", "solver.substeps=" + "[" * 5000 + "]" * 5000],
         needle="nested too deeply", files={"scene.toml": GOOD}),
    Case("set-wrong-type", ["run", "{tmp}/scene.toml", "--set", "solver.substeps=[1,2]"], needle="solver.substeps",
         files={"scene.toml": GOOD}),
    Case("workers-0", ["sweep", "{tmp}/scene.toml", "--param", "substeps=1,2", "--workers", "0"],
         needle="--workers", files={"scene.toml": GOOD}),
    Case("sweep-param-unknown", ["sweep", "{tmp}/scene.toml", "--param", "nothing=1,2", "--out", "{tmp}/s"],
         needle="--param nothing", files={"scene.toml": GOOD}),
    Case("sweep-param-malformed", ["sweep", "{tmp}/scene.toml", "--param", "substeps", "--out", "{tmp}/s"],
         needle="--param", files={"scene.toml": GOOD}),
    # -- scene paths
    Case("scene-missing", ["run", "{tmp}/none.toml"], needle="no such scene file"),
    Case("scene-unknown-name", ["run", "no_such_example"], needle="nor an example scene"),
    Case("scene-is-folder", ["run", "{tmp}/folder"], needle="is a folder", files={"folder/x": ""}),
    Case("scene-toml-folder", ["run", "{tmp}/dir.toml"], needle="is a folder", files={"dir.toml/x": ""}),
    Case("example-beside-same-folder", ["run", "vortex_sheet", "--out", "{tmp}/o", *QUICK], expect="ok",
         files={"vortex_sheet/x": ""}, cwd_tmp=True),
    # -- malformed scene files
    Case("empty-file", ["run", "{tmp}/scene.toml"], needle="solver: missing required table", files={"scene.toml": ""}),
    Case("not-toml", ["run", "{tmp}/scene.toml"], needle="not valid TOML", files={"scene.toml": "[scene\nx=="}),
    Case("binary-file", ["run", "{tmp}/scene.toml"], needle="scene.toml", files={"scene.toml": b"\xff\xfe\x00\x81" * 64}),
    Case("deep-arrays", ["run", "{tmp}/scene.toml"], needle="nested too deeply", files={"scene.toml": DEEP}),
    Case("deep-tables", ["run", "{tmp}/scene.toml"], needle="nested too deeply",
         files={"scene.toml": "a = " + "{b = " * 50000 + "1" + "}" * 50000 + "\n"}),
    Case("unknown-table", ["run", "{tmp}/scene.toml"], needle="scenery: unknown table",
         files={"scene.toml": "[scenery]\n" + GOOD}),
    Case("duration-text", ["run", "{tmp}/scene.toml"], needle="scene.duration: expected a number",
         files={"scene.toml": _scene(**{"duration = 0.1": 'duration = "long"'})}),
    Case("duration-nan", ["run", "{tmp}/scene.toml"], needle="scene.duration",
         files={"scene.toml": _scene(**{"duration = 0.1": "duration = nan"})}),
    Case("duration-inf", ["run", "{tmp}/scene.toml"], needle="scene.duration",
         files={"scene.toml": _scene(**{"duration = 0.1": "duration = inf"})}),
    Case("duration-absurd", ["run", "{tmp}/scene.toml"], needle="scene.duration: 1e+300 s",
         files={"scene.toml": _scene(**{"duration = 0.1": "duration = 1e300"})}),
    Case("fps-absurd", ["run", "{tmp}/scene.toml"], needle="frames, more than",
         files={"scene.toml": _scene(**{"fps = 20": "fps = 1e12"})}),
    Case("substeps-absurd", ["run", "{tmp}/scene.toml"], needle="solver.substeps: the run would take",
         files={"scene.toml": _scene(**{"substeps = 1": "substeps = 4611686018427387904"})}),
    Case("grid-max-dt-tiny", ["run", "{tmp}/scene.toml"], needle="solver.max_dt: the run would take",
         files={"scene.toml": '[scene]\nname = "g"\nduration = 1\n[solver]\ntype = "grid"\nresolution = [8, 8]\n'
                              'max_dt = 1e-300\n[[objects]]\ntype = "obstacle"\n'
                              'region = { shape = "sphere", center = [0.5, 0.5], radius = 0.1 }\n'}),
    Case("grid-resolution-oom", ["run", "{tmp}/scene.toml"], needle="solver.resolution: about",
         files={"scene.toml": '[scene]\nname = "g"\nduration = 1\n[solver]\ntype = "grid"\n'
                              'resolution = [100000, 100000, 100000]\n[[objects]]\ntype = "obstacle"\n'
                              'region = { shape = "sphere", center = [0.5, 0.5, 0.5], radius = 0.1 }\n'}),
    Case("sph-spacing-oom", ["run", "{tmp}/scene.toml"], needle="solver.spacing: about",
         files={"scene.toml": '[scene]\nname = "s"\nduration = 1\n[solver]\ntype = "sph"\nspacing = 1e-7\n'
                              'domain = { lower = [0, 0], upper = [1, 1] }\n[[objects]]\ntype = "fluid"\n'
                              'region = { shape = "box", lower = [0, 0], upper = [0.5, 0.5] }\n'}),
    Case("image-oom", ["run", "{tmp}/scene.toml"], needle="output.width, output.height: about",
         files={"scene.toml": _scene(**{"width = 32": "width = 10000000"})}),
    Case("vortex-particles-oom", ["run", "{tmp}/scene.toml"], needle="objects[0].particles",
         files={"scene.toml": _scene(**{"particles = 16": "particles = 9000000000000000000"})}),
    Case("frames-times-substeps", ["run", "{tmp}/scene.toml", "--frames", "1000000"],
         needle="frames: 1000000 frames would take at least",
         files={"scene.toml": _scene(**{"substeps = 1": "substeps = 10000"})}),
    Case("colormap-unknown", ["run", "{tmp}/scene.toml"], needle="output.colormap: expected a matplotlib colormap",
         files={"scene.toml": _scene(**{"width = 32": 'width = 32\ncolormap = "rainbowz"'})}),
    Case("out-of-memory-at-build", ["run", "{tmp}/scene.toml", "--out", "{tmp}/o", *QUICK], needle="out of memory",
         files={"scene.toml": GOOD}, patch=_bad_alloc),
    # -- output paths
    Case("out-is-file", ["run", "{tmp}/scene.toml", "--out", "{tmp}/file", *QUICK], needle="{tmp}/file is a file",
         files={"scene.toml": GOOD, "file": "x"}),
    Case("out-foreign-folder", ["run", "{tmp}/scene.toml", "--out", "{tmp}/mine", *QUICK],
         needle="is not empty and holds no kinema run", files={"scene.toml": GOOD, "mine/thesis.tex": "x"}),
    Case("out-earlier-run", ["run", "{tmp}/scene.toml", "--out", "{tmp}/out", *QUICK], expect="ok",
         files={"scene.toml": GOOD}, run_first=True),
    Case("disk-full", ["run", "{tmp}/scene.toml", "--out", "{tmp}/o", *QUICK],
         needle="{tmp}/o/frames/frame_00000.png: No space left on device", files={"scene.toml": GOOD}, patch=_enospc),
    Case("read-only-out", ["run", "{tmp}/scene.toml", "--out", "{tmp}/o", *QUICK], needle="Permission denied",
         files={"scene.toml": GOOD}, patch=_read_only),
    Case("resume-without-folder", ["run", "{tmp}/scene.toml", "--out", "{tmp}/none", "--resume", *QUICK],
         needle="--resume: no checkpoint", files={"scene.toml": GOOD}),
    # -- damaged checkpoints: one line naming the file, the folder untouched
    Case("checkpoint-truncated", RESUME,
         needle="{tmp}/out/checkpoint.npz: damaged checkpoint", files={"scene.toml": GOOD}, run_first=True,
         damage=_truncate, untouched=True),
    Case("checkpoint-empty", RESUME,
         needle="checkpoint.npz: damaged checkpoint", files={"scene.toml": GOOD}, run_first=True,
         damage=lambda p: p.write_bytes(b""), untouched=True),
    Case("checkpoint-bit-flips", RESUME,
         needle="checkpoint.npz: damaged checkpoint", files={"scene.toml": GOOD}, run_first=True, damage=_flip,
         untouched=True),
    Case("checkpoint-no-time", RESUME,
         needle="checkpoint.npz: damaged checkpoint (state", files={"scene.toml": GOOD}, run_first=True,
         damage=_rewrite(drop=["state/time"]), untouched=True),
    Case("checkpoint-no-frame", RESUME,
         needle="meta.frame missing", files={"scene.toml": GOOD}, run_first=True,
         damage=_rewrite(meta={"frame": _DROP}), untouched=True),
    Case("checkpoint-frame-text", RESUME,
         needle="meta.frame", files={"scene.toml": GOOD}, run_first=True,
         damage=_rewrite(meta={"frame": "two"}), untouched=True),
    Case("checkpoint-wrong-shape", RESUME,
         needle="checkpoint", files={"scene.toml": GOOD}, run_first=True,
         damage=_rewrite(state={"state/x": np.zeros((3, 7))}), untouched=True),
    Case("checkpoint-text-array", RESUME,
         needle="checkpoint", files={"scene.toml": GOOD}, run_first=True,
         damage=_rewrite(state={"state/time": np.array("soon")}), untouched=True),
    Case("checkpoint-meta-not-json", RESUME,
         needle="checkpoint.npz: damaged checkpoint", files={"scene.toml": GOOD}, run_first=True,
         damage=lambda p: np.savez(p, meta=np.array("{not json")), untouched=True),
    Case("checkpoint-folder", RESUME,
         needle="checkpoint.npz: is a folder", files={"scene.toml": GOOD}, run_first=True,
         damage=lambda p: (p.unlink(), p.mkdir()), untouched=True),
    Case("resume-ok", RESUME, expect="ok", files={"scene.toml": GOOD}, run_first=True),
]

# Colliders of fem and mass-spring scenes: objects[1] is the collider each case changes.
BODY = {"fem": fem_box((0.0, 0.05, 0.0), (0.1, 0.15, 0.1), youngs_modulus=1e4, density=1000.0),
        "massspring": cloth((3, 3), (0.2, 0.2), (0.0, 0.1, 0.0), stiffness=100.0, mass=0.05)}


def _collider(collider, solver="", kind="fem"):
    return (f'[scene]\nname = "c"\nduration = 0.04\nfps = 50\n[solver]\ntype = "{kind}"\n'
            f'gravity = [0.0, -9.81, 0.0]\n{solver}\n[[objects]]\n{BODY[kind]}\n[[objects]]\ntype = "collider"\n'
            f'{collider}\n[output]\nwidth = 32\n')


SPHERE = 'shape = "sphere"\ncenter = [0.05, -0.5, 0.05]\nradius = 0.5'
RUN = ["run", "{tmp}/scene.toml", "--out", "{tmp}/o", *QUICK]
BOX = 'shape = "box"\nlower = [-1.0, -1.0, -1.0]\nupper = [1.0, 0.0, 1.0]'
PLANE = 'shape = "plane"\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 0.0, 0.0]'
# (case, the collider's keys, the [solver] lines, the error's needle, extra files); "ok": no error
COLLIDER_CASES = [
    ("collider-ok", SPHERE, "", None, {}),
    ("collider-radius-negative", SPHERE.replace("radius = 0.5", "radius = -1.0"), "", "objects[1].radius", {}),
    ("collider-no-radius", 'shape = "sphere"\ncenter = [0.0, -1.0, 0.0]', "",
     "objects[1].radius: a sphere collider needs radius", {}),
    ("collider-box-no-upper", 'shape = "box"\nlower = [0.0, -1.0, 0.0]', "", "objects[1].upper: a box collider needs upper",
     {}),
    ("collider-box-inverted", 'shape = "box"\nlower = [1.0, 0.0, 1.0]\nupper = [-1.0, -1.0, -1.0]', "",
     "objects[1]: lower, upper: expected lower < upper", {}),
    ("collider-box-rotation-nan", BOX + "\nrotation = [nan, 0.0, 0.0]", "", "objects[1].rotation", {}),
    ("collider-plane-zero-normal", PLANE, "", "objects[1]: normal: expected a non-zero vector", {}),
    ("collider-plane-moving", PLANE.replace("normal = [0.0, 0.0, 0.0]", "normal = [0.0, 1.0, 0.0]") +
     "\nvelocity = [0.0, 1.0, 0.0]", "", None, {}),
    ("collider-center-2d", 'shape = "sphere"\ncenter = [0.0, -1.0]\nradius = 0.5', "", "objects[1].center", {}),
    ("collider-center-inf", 'shape = "sphere"\ncenter = [0.0, -inf, 0.0]\nradius = 0.5', "", "objects[1].center", {}),
    ("collider-velocity-text", SPHERE + '\nvelocity = "up"', "", "objects[1].velocity", {}),
    ("collider-unknown-key", SPHERE + "\nradius2 = 1.0", "", "objects[1].radius2", {}),
    ("collider-unknown-shape", 'shape = "cone"\nradius = 1.0', "", "objects[1].shape", {}),
    ("collider-friction-negative", SPHERE + "\nfriction = -0.1", "", "objects[1].friction", {}),
    ("collider-mesh-missing", 'shape = "mesh"\nfile = "none.obj"', "", "objects[1].file", {}),
    ("collider-mesh-garbage", 'shape = "mesh"\nfile = "g.obj"', "", "objects[1].file", {"g.obj": bytes(range(256))}),
    ("collider-mesh-no-triangles", 'shape = "mesh"\nfile = "l.obj"', "", "objects[1].file",
     {"l.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n"}),
    ("dhat-zero", SPHERE, "dhat = 0.0", "solver.dhat", {}),
]
for kind in ("fem", "massspring"):
    CASES += [Case(f"{kind}-{name}", RUN, **({"expect": "ok"} if needle is None else {"needle": needle}),
                   files={"scene.toml": _collider(collider, solver, kind=kind), **extra})
              for name, collider, solver, needle, extra in COLLIDER_CASES]
CASES += [
    Case("fem-collider-symplectic", RUN, needle="solver.integrator",
         files={"scene.toml": _collider(SPHERE, 'integrator = "symplectic"\n[[objects]]\n' + fem_box(
             (0.3, 0.05, 0.0), (0.4, 0.15, 0.1), youngs_modulus=1e4, density=1000.0))}),
    Case("massspring-collider-rotated-box-symplectic", RUN, needle="solver.integrator: integrator: a mesh collider",
         files={"scene.toml": _collider('shape = "box"\nlower = [-1.0, -1.0, -1.0]\nupper = [1.0, 0.0, 1.0]\n'
                                        'rotation = [0.0, 0.0, 10.0]', 'integrator = "symplectic"', kind="massspring")}),
    Case("massspring-collider-intersecting-start", RUN, needle="intersect",
         files={"scene.toml": _collider('shape = "box"\nlower = [0.05, 0.0, 0.05]\nupper = [0.15, 0.2, 0.15]',
                                        kind="massspring")}),
]


def _prepare(case, tmp):
    for rel, content in case.files.items():
        p = tmp / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    if case.run_first:
        import kinema as km

        km.Scene.load(tmp / "scene.toml", quick=True, overrides=[("output.mp4", False)]).run(
            tmp / "out", 2, progress=False)
        if case.damage is not None:
            case.damage(tmp / "out" / "checkpoint.npz")


def _snapshot(folder):
    if not folder.exists():
        return None
    return {str(p.relative_to(folder)): (p.is_dir(), p.stat().st_mtime_ns, p.stat().st_size)
            for p in folder.rglob("*")}


def _argv(case, tmp):
    return [a.replace("{tmp}", str(tmp)) for a in case.argv]


def classify(case, tmp, code, err, before):
    """One of OUTCOMES for a finished case."""
    if code is None:
        return "hang"
    if "Traceback" in err:
        return "traceback"
    if code < 0:
        return "crash"
    if case.expect == "ok":
        return "ok" if code == 0 else "wrong"
    lines = [line for line in err.strip().splitlines() if line.strip()]
    if code not in (1, 2) or not lines:
        return "wrong"
    if len(lines) != 1:
        return "multi-line"
    if not lines[0].startswith("kinema") or case.needle.replace("{tmp}", str(tmp)) not in lines[0]:
        return "wrong"
    if case.untouched and _snapshot(tmp / "out") != before:
        return "wrong"
    return "error"


def run_in_process(case, tmp, capsys, monkeypatch):
    from kinema.cli import main

    _prepare(case, tmp)
    before = _snapshot(tmp / "out")
    capsys.readouterr()
    if case.cwd_tmp:
        monkeypatch.chdir(tmp)
    if case.patch is not None:
        case.patch(monkeypatch)
    try:
        code = main(_argv(case, tmp))
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 2
    except BaseException as exc:  # an escaping exception is the traceback a user would see
        monkeypatch.undo()
        return "traceback", f"Traceback: {exc.__class__.__name__}: {exc}"
    monkeypatch.undo()
    err = capsys.readouterr().err
    return classify(case, tmp, code, err, before), err


def run_process(case, tmp, python=sys.executable, timeout=120):
    _prepare(case, tmp)
    before = _snapshot(tmp / "out")
    try:
        done = subprocess.run([python, "-m", "kinema.cli", *_argv(case, tmp)], capture_output=True, text=True,
                              timeout=timeout, cwd=tmp if case.cwd_tmp else None, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return "hang", ""
    return classify(case, tmp, done.returncode, done.stderr, before), done.stderr


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_cli_case_in_process(case, tmp_path, capsys, monkeypatch):
    outcome, err = run_in_process(case, tmp_path, capsys, monkeypatch)
    assert outcome == case.expect, f"{case.name}: {outcome}\n{err}"


@pytest.mark.slow
def test_cli_cases_as_processes(tmp_path):
    counts = collections.Counter()
    bad = []
    for k, case in enumerate(c for c in CASES if c.patch is None):
        folder = tmp_path / f"case{k}"
        folder.mkdir()
        outcome, err = run_process(case, folder)
        counts[outcome] += 1
        if outcome != case.expect:
            bad.append(f"{case.name}: {outcome}: {err.strip()[-300:]}")
    print("outcomes:", dict(counts))
    assert not bad, "\n".join(bad)


def main(argv=None):
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--python", default=sys.executable, help="the interpreter whose kinema is tested")
    args = p.parse_args(argv)
    counts = collections.Counter()
    for case in (c for c in CASES if c.patch is None):
        tmp = Path(tempfile.mkdtemp(prefix="kinema-fuzz-"))
        try:
            outcome, err = run_process(case, tmp, args.python)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        counts[outcome] += 1
        last = err.strip().splitlines()[-1] if err.strip() else ""
        print(f"{outcome:11s} {case.name:28s} {last[:110]}")
    print("outcomes:", ", ".join(f"{k} {counts[k]}" for k in OUTCOMES if counts[k]))


if __name__ == "__main__":
    main()
