"""The frame loop of ``Scene.run`` / ``kinema run``: step, write, checkpoint, report progress.

Layout of the output folder::

    frames/frame_00000.png ...     preview images (output.png)
    video.mp4                      the frames as a video (output.mp4, ffmpeg)
    <name>/<name>_00000.vtu|ply|vti  data files every output.every frames
    checkpoint.npz                 the state after the last frame written (kinema run --resume)
    diagnostics.csv                one row per frame: time, steps, the solver's diagnostics
"""

from __future__ import annotations

import contextlib
import csv
import io
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import kinema as km
from kinema.scenes import output as io_out
from kinema.scenes.adapters.base import GridData


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


def _write_data(out, item, frame, fmt):
    folder = out / item.name
    folder.mkdir(exist_ok=True)
    path = folder / f"{item.name}_{frame:05d}.{fmt}"
    if isinstance(item, GridData):
        io_out.write_vti(path, item.fields, item.h)
    elif fmt == "ply":
        cells = [("triangle", item.surface)] if item.surface is not None else []
        io_out.write_mesh(path, item.points, cells, item.point_data, "ply")
    else:
        io_out.write_mesh(path, item.points, item.cells, item.point_data, "vtu")


def _write_frame(scene, sim, out, frame):
    o = scene.config["output"]
    if o["png"]:
        io_out.write_png(out / "frames" / f"frame_{frame:05d}.png", sim.image(o))
    if frame % o["every"] == 0 and (o["vtu"] or o["ply"] or o["vti"]):
        for item in sim.data():
            formats = ["vti"] if isinstance(item, GridData) else ["vtu", "ply"]
            for fmt in formats:
                if o[fmt]:
                    _write_data(out, item, frame, fmt)


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
    out.mkdir(parents=True, exist_ok=True)
    (out / "frames").mkdir(exist_ok=True)
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
    sim = scene.build()
    checkpoint = out / "checkpoint.npz"
    start = 0
    if resume:
        if not checkpoint.exists():
            raise FileNotFoundError(f"--resume: no checkpoint in {out} (run without --resume first)")
        state, meta = io_out.load_checkpoint(checkpoint)
        if meta["fingerprint"] != scene.fingerprint():
            raise ValueError(f"--resume: {checkpoint} was written by a different scene or different "
                             f"solver/object settings ({meta['scene']}); run without --resume")
        sim.set_state(state)
        start = meta["frame"] + 1
    stream = None if progress is False else sys.stderr if progress is True else progress
    bar = Progress(stream, frames, start) if stream is not None else None
    result = RunResult(out=out, frames=start)
    t0 = time.perf_counter()
    try:
        for frame in range(start, frames):
            steps = sim.advance_to(frame / scene.fps) if frame > 0 else 0
            result.steps += steps
            with _frame_commit():
                _write_frame(scene, sim, out, frame)
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
    result.seconds = time.perf_counter() - t0
    result.time = sim.time
    if o["png"] and o["mp4"] and result.frames > 1:
        video = out / "video.mp4"
        if io_out.write_mp4(video, out / "frames" / "frame_%05d.png", scene.fps):
            result.video = video
    if bar:
        what = "interrupted" if result.interrupted else "done"
        bar.finish(f"{what}: {result.frames} frames, {result.steps} steps in {result.seconds:.1f} s -> {out}")
    if result.interrupted:
        raise KeyboardInterrupt(result)
    return result
