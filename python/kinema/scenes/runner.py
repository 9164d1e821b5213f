"""The frame loop of ``Scene.run`` / ``kinema run``: step, write, checkpoint, report progress.

Layout of the output folder::

    frames/frame_00000.png ...     preview images (output.png)
    video.mp4                      the frames as a video (output.mp4, ffmpeg)
    <name>/<name>_00000.vtu|ply|vti  data files every output.every frames (kinema.io)
    <name>.pvd                     the VTU/VTI files with their simulated times (ParaView)
    checkpoint.npz                 the state after the last frame written (kinema run --resume)
    diagnostics.csv                one row per frame: time, steps, the solver's diagnostics
    run.json                       which scene wrote the folder

A run into a folder that holds an earlier run starts clean: the earlier run's files (those
named above) are removed first, and the run says so. A folder that is not empty and holds no
run is refused. ``resume=True`` continues the run in the folder instead.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import kinema as km
from kinema.scenes import output as io_out
from kinema.scenes.adapters.base import GridData
from kinema.scenes.scene import MAX_FRAMES, MAX_STEPS, min_steps


@dataclass
class RunResult:
    """What a run did: frames written in total (this run: ``new_frames``), solver steps of this
    run, wall seconds, the last diagnostics, and whether Ctrl-C stopped it."""

    out: Path
    frames: int
    new_frames: int = 0
    steps: int = 0
    seconds: float = 0.0
    time: float = 0.0
    diagnostics: dict = field(default_factory=dict)
    interrupted: bool = False
    video: Path | None = None
    #: what the user should know (an earlier run replaced, no video without ffmpeg)
    notes: list = field(default_factory=list)

    def summary(self):
        """The run's final line: frames, steps, seconds and the folder."""
        what = "interrupted" if self.interrupted else "done"
        return f"{what}: {self.frames} frames, {self.steps} steps in {self.seconds:.1f} s -> {self.out}"


class Progress:
    """A one-line progress bar (frames, simulated time, steps per second, ETA) on a terminal,
    or plain lines (about every 10% and the last frame) when the stream is not one."""

    def __init__(self, stream, total, start):
        self.stream, self.total, self.start = stream, total, start
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.t0 = time.perf_counter()
        self.every = max(1, (total - start) // 10)

    def update(self, frame, sim_time, steps):
        done = frame + 1
        elapsed = time.perf_counter() - self.t0
        new = done - self.start
        rate = steps / elapsed if elapsed > 0 else 0.0
        eta = elapsed / new * (self.total - done) if new > 0 else 0.0
        text = (f"{done}/{self.total} frames  t = {sim_time:.3f} s  {rate:.0f} steps/s  "
                f"ETA {int(eta) // 60}:{int(eta) % 60:02d}")
        if self.tty:
            width = 24
            fill = int(width * done / self.total)
            self.stream.write(f"\r[{'#' * fill}{'.' * (width - fill)}] {text}\033[K")
            if done == self.total:
                self.stream.write("\n")
        elif new % self.every == 0 or done == self.total:
            self.stream.write(text + "\n")
        self.stream.flush()

    def finish(self, message):
        if self.tty:
            self.stream.write("\n")
        self.stream.write(message + "\n")
        self.stream.flush()


def _write_data(out, item, frame, fmt, series):
    path = out / item.name / f"{item.name}_{frame:05d}.{fmt}"
    if isinstance(item, GridData):
        km.io.write_grid(path, item.fields, item.h)
    elif fmt == "ply" and item.surface is not None:
        km.io.write_mesh(path, item.points, item.surface, item.point_data)
    elif fmt == "vtu" and item.cells:
        km.io.write_mesh(path, item.points, item.cells, item.point_data)
    else:
        km.io.write_particles(path, item.points, item.point_data, ids=item.ids)
    if fmt in ("vtu", "vti"):
        key = (item.name, fmt)
        if key not in series:
            series[key] = km.io.Series(out / f"{item.name}.pvd", resume=True)
        return path, series[key]
    return path, None


def _write_frame(scene, sim, out, frame, series):
    o = scene.config["output"]
    if o["png"]:
        io_out.write_png(out / "frames" / f"frame_{frame:05d}.png", sim.image(o))
    if frame % o["every"] == 0 and (o["vtu"] or o["ply"] or o["vti"]):
        for item in sim.data():
            formats = ["vti"] if isinstance(item, GridData) else ["vtu", "ply"]
            for fmt in formats:
                if o[fmt]:
                    path, listing = _write_data(out, item, frame, fmt, series)
                    if listing is not None:
                        listing.add(sim.time, path)


_MARKER = "run.json"
_RUN_FILES = ("video.mp4", "checkpoint.npz", "diagnostics.csv", _MARKER)


def _holds_run(out):
    return any((out / name).is_file() for name in ("run.json", "checkpoint.npz", "diagnostics.csv"))


def _clear_run(out):
    """Removes the files of an earlier run in ``out`` (and only those)."""
    for name in _RUN_FILES:
        with contextlib.suppress(FileNotFoundError):
            (out / name).unlink()
    for p in out.glob("*.pvd"):
        p.unlink()
    for p in out.glob(".*.tmp"):  # left by a killed run
        p.unlink()
    for folder in [d for d in out.iterdir() if d.is_dir()]:
        pattern = re.compile(r"frame_\d+\.png" if folder.name == "frames"
                             else re.escape(folder.name) + r"_\d+\.(vtu|ply|vti)")
        for p in folder.iterdir():
            if p.is_file() and (pattern.fullmatch(p.name) or (p.name.startswith(".") and p.name.endswith(".tmp"))):
                p.unlink()
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty


def _prepare(scene, out, resume):
    """Makes ``out`` ready for a run: returns (created, notes). Refuses a file, and a folder
    with other content than an earlier run's."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} is a file, expected a folder")
    notes = []
    created = not out.exists()
    if resume:
        if created:
            raise FileNotFoundError(f"--resume: no folder {out} (run without --resume first)")
    elif not created and any(out.iterdir()):
        if not _holds_run(out):
            raise ValueError(f"out: {out} is not empty and holds no kinema run; choose a new or empty folder "
                             "(kinema replaces only its own earlier runs)")
        _clear_run(out)
        notes.append(f"{out} held an earlier run: its frames, data files, video and checkpoint were removed "
                     "(use --resume to continue a run instead)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "frames").mkdir(exist_ok=True)
    with io_out.atomic_path(out / _MARKER) as tmp:
        tmp.write_text(json.dumps({"scene": scene.name, "path": scene.path, "solver": scene.solver,
                                   "fingerprint": scene.fingerprint(), "kinema": km.__version__}, indent=1))
    return created, notes


@contextlib.contextmanager
def _frame_commit():
    """Holds Ctrl-C back while a frame's files and the checkpoint are written, so that the
    folder always holds whole frames up to the checkpoint's; the interrupt is raised after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def _append_diagnostics(out, row):
    """Rewrites diagnostics.csv with one more row (atomically: read, append, replace)."""
    path = out / "diagnostics.csv"
    rows = []
    if path.exists():
        with open(path, newline="") as fh:
            rows = [r for r in csv.DictReader(fh) if int(r["frame"]) < row["frame"]]
    rows.append(row)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(row))
    writer.writeheader()
    writer.writerows(rows)
    with io_out.atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())


def run(scene, out, frames=None, *, resume=False, progress=True, on_frame=None):
    out = Path(out)
    frames = scene.default_frames if frames is None else int(frames)
    if frames < 1:
        raise ValueError(f"frames: expected an integer >= 1, got {frames}")
    if frames > MAX_FRAMES:
        raise ValueError(f"frames: expected at most {MAX_FRAMES:,}, got {frames}")
    steps, why = min_steps(scene.config, frames)
    if steps > MAX_STEPS:
        raise ValueError(f"frames: {frames} frames would take at least {steps:.3g} solver steps ({why}), "
                         f"more than {MAX_STEPS:,}")
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} is a file, expected a folder")
    threads = scene.config["scene"]["threads"]
    previous_threads = km.get_num_threads()
    if threads:
        km.set_num_threads(threads)
    try:
        return _run(scene, out, frames, resume, progress, on_frame)
    finally:
        km.set_num_threads(previous_threads)


def _run(scene, out, frames, resume, progress, on_frame):
    o = scene.config["output"]
    sim = scene.build()  # before the folder is touched: a scene that fails here writes nothing
    checkpoint = out / "checkpoint.npz"
    start = 0
    if resume:
        if not checkpoint.exists():
            raise FileNotFoundError(f"--resume: no checkpoint in {out} (run without --resume first)")
        state, meta = io_out.load_checkpoint(checkpoint)
        if meta["fingerprint"] != scene.fingerprint():
            raise ValueError(f"--resume: {checkpoint} was written by a different scene or different "
                             f"solver/object settings ({meta.get('scene')}); resume with the scene and "
                             "--set options of the run that wrote it, or run without --resume")
        try:
            sim.set_state(state)
        except (KeyError, ValueError, TypeError) as exc:
            raise io_out.CheckpointError(f"{checkpoint}: damaged checkpoint (state {exc}); run without --resume "
                                         "to start over") from None
        start = meta["frame"] + 1
    created, notes = _prepare(scene, out, resume)
    stream = None if progress is False else sys.stderr if progress is True else progress
    bar = Progress(stream, frames, start) if stream is not None else None
    result = RunResult(out=out, frames=start, notes=notes)
    if bar:
        for note in notes:
            stream.write(f"kinema: {note}\n")
    series = {}
    t0 = time.perf_counter()
    try:
        for frame in range(start, frames):
            steps = sim.advance_to(frame / scene.fps) if frame > 0 else 0
            result.steps += steps
            with _frame_commit():
                _write_frame(scene, sim, out, frame, series)
                result.diagnostics = sim.diagnostics()
                _append_diagnostics(out, {"frame": frame, "time": sim.time, "steps": sim.steps,
                                          **result.diagnostics})
                if frame % o["checkpoint_every"] == 0 or frame == frames - 1:
                    io_out.save_checkpoint(checkpoint, sim.get_state(),
                                           {"frame": frame, "fingerprint": scene.fingerprint(), "scene": scene.name,
                                            "solver": scene.solver, "kinema": km.__version__})
                result.frames = frame + 1
                result.new_frames += 1
            if bar:
                bar.update(frame, sim.time, result.steps)
            if on_frame is not None:
                on_frame(frame, sim)
    except KeyboardInterrupt:
        result.interrupted = True
    except BaseException:
        # Nothing of this run is worth keeping when it fails before its first frame.
        if created and result.new_frames == 0:
            shutil.rmtree(out, ignore_errors=True)
        raise
    result.seconds = time.perf_counter() - t0
    result.time = sim.time
    if o["png"] and o["mp4"] and result.frames > 1:
        video = out / "video.mp4"
        if io_out.write_mp4(video, out / "frames" / "frame_%05d.png", scene.fps):
            result.video = video
        else:
            result.notes.append("ffmpeg not found: no video.mp4 (install ffmpeg, e.g. apt-get install ffmpeg, "
                                "or set output.mp4 = false)")
            if bar:
                stream.write(f"kinema: {result.notes[-1]}\n")
    if bar:
        bar.finish(result.summary())
    if result.interrupted:
        raise KeyboardInterrupt(result)
    return result
