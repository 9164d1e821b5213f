"""Frames per second of the live viewer (km.viewer on Polyscope) at 1e5 and 1e6 particles, on
whatever OpenGL the display offers (here: Mesa's llvmpipe software rasteriser under Xvfb).

    python bench/render/viewer_bench.py                   # 1e4, 1e5, 1e6 particles, 1024x768
    python bench/render/viewer_bench.py --sizes 100000 --width 640 --height 480
    python bench/render/viewer_bench.py --points splat --splat-scale 1.0

A frame is what the window does while a simulation runs: new positions and a new colour
quantity (speed) uploaded, then drawn and presented (Viewer.tick with a CallbackSource that
moves the particles: a ball of n particles rotating about the vertical axis, so the work per
frame does not change). Each size is drawn both ways, in the same run: Polyscope's own sphere
impostors (points="polyscope") and kinema's CPU splat composited by depth (points="splat", the
viewer's choice above kv.SPLAT_ABOVE particles). Before a time is recorded, a screenshot must show the particles'
colours inside the ball's projection. The time of 20 frames after 3 warm-up frames is timed by
bench/common/harness.py (other processes' load recorded, disturbed runs retried). Starts an Xvfb when
no DISPLAY is set. CSV: bench/out/viewer.csv.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

import kinema as km  # noqa: E402
from kinema import viewer as kv  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "out"


def ensure_display():
    if os.environ.get("DISPLAY"):
        return None
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise SystemExit("no DISPLAY and no Xvfb (apt-get install xvfb libgl1-mesa-dri)")
    number = next(n for n in range(140, 200) if not os.path.exists(f"/tmp/.X11-unix/X{n}"))
    proc = subprocess.Popen([xvfb, f":{number}", "-screen", "0", "1920x1080x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        if os.path.exists(f"/tmp/.X11-unix/X{number}"):
            break
        time.sleep(0.05)
    os.environ["DISPLAY"] = f":{number}"
    return proc


class Ball:
    """n particles in a unit ball turning about y; speed as the colour quantity."""

    def __init__(self, n):
        rng = np.random.default_rng(0)
        x = rng.normal(size=(n, 3))
        self.x0 = x / np.linalg.norm(x, axis=1, keepdims=True) * rng.random((n, 1)) ** (1 / 3)
        self.k = 0

    def step(self):
        self.k += 1
        return 1

    def items(self):
        a = 0.01 * self.k
        c, s = np.cos(a), np.sin(a)
        x = self.x0 @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        speed = np.hypot(x[:, 0], x[:, 2])
        return {"particles": (x, {"speed": speed})}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="*", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--width", type=int, default=1024)
    p.add_argument("--height", type=int, default=768)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--points", nargs="*", default=["polyscope", "splat"], choices=["polyscope", "splat"])
    p.add_argument("--splat-scale", type=float, default=0.5)
    args = p.parse_args(argv)
    xvfb = ensure_display()
    rec = harness.Recorder(OUT / "viewer.csv", "viewer_fps", threads=km.get_num_threads())
    try:
        for n, points in ((n, points) for n in args.sizes for points in args.points):
            ball = Ball(n)
            v = kv.Viewer(kv.CallbackSource(ball.step, ball.items, name="ball"), point_radius=0.6 / n ** (1 / 3),
                          width=args.width, height=args.height, points=points, splat_scale=args.splat_scale)
            renderer = v.ps.get_render_engine_backend_name() if hasattr(v.ps, "get_render_engine_backend_name") else ""
            v.tick(3)
            img = v.screenshot()
            col, row = v.project(np.array([[0.0, 0.0, 0.0]]))
            centre = img[int(row[0]) - 5:int(row[0]) + 5, int(col[0]) - 5:int(col[0]) + 5].astype(int)
            if np.abs(centre - img[2, 2].astype(int)).sum(axis=-1).mean() < 30:
                raise AssertionError(f"n={n}: the ball's centre shows the background; not recording")
            m = harness.measure(lambda: v.tick(args.frames), min_of=2, max_tries=3)
            fps = args.frames / m.seconds
            rec.record(f"viewer-{points}", n, m.seconds / args.frames,
                       measurement=m, notes={"fps": f"{fps:.2f}", "window": f"{args.width}x{args.height}",
                                             "gl": "mesa-llvmpipe-xvfb", "backend": renderer,
                                             "splat_scale": args.splat_scale})
            print(f"{n:9d} particles  {points:9s} {fps:7.2f} fps  ({m.seconds / args.frames * 1e3:7.1f} ms/frame, "
                  f"other load {m.other_load:.2f} cores{', disturbed' if m.disturbed else ''})", flush=True)
            v.close()
    finally:
        if xvfb is not None:
            if kv._initialised:
                import polyscope as ps

                ps.shutdown()
            xvfb.terminate()


if __name__ == "__main__":
    main()
