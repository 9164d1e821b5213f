"""Regenerates the README's gallery (docs/gallery/*.png) with kinema's own command line: every
shipped example scene at its default settings, run with `kinema run` to a moment where
something happens, its last frame halved to a small PNG.

    .venv/bin/python scripts/gallery.py [NAME ...] [--out docs/gallery]

Only the frames are written (the data files and the video are switched off with --set: they do
not change the pictures). Takes a few minutes on 2 cores (the 3D dam break and smoke dominate).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The fraction of each scene's duration at which its picture is taken.
MOMENT = {"dam_break": 0.27, "hanging_cloth": 0.67, "smoke_plume": 0.6, "smoke_plume_3d": 0.6,
          "soft_body": 0.2, "vortex_merge": 0.5, "vortex_sheet": 0.5,
          "soft_cube_pile": 0.7, "jelly_stairs": 0.4, "cloth_drape": 0.5}
OFF = ["output.mp4=false", "output.vtu=false", "output.ply=false", "output.vti=false", "output.png=true"]


def halve(img):
    """Box filter to half size (small PNGs for the README)."""
    h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
    x = img[:h, :w].astype(float)
    return ((x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2]) / 4).round().astype(np.uint8)


def main(argv=None):
    import kinema as km
    from matplotlib import image as mpl_image

    from kinema.scenes import examples
    from kinema.scenes.output import write_png

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("names", nargs="*", help="example scenes (default: all)")
    p.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "docs" / "gallery"))
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    kinema = Path(sys.executable).with_name("kinema")
    for name, path in examples().items():
        if args.names and name not in args.names:
            continue
        scene = km.Scene.load(path)
        frames = max(2, round(MOMENT.get(name, 0.5) * (scene.default_frames - 1)) + 1)
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [str(kinema), "run", name, "--out", tmp, "--frames", str(frames), "--no-progress"]
            for item in OFF:
                cmd += ["--set", item]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True)
            frame = Path(tmp) / "frames" / f"frame_{frames - 1:05d}.png"
            img = (mpl_image.imread(frame)[..., :3] * 255).round().astype(np.uint8)
            target = out / f"{name}.png"
            write_png(target, halve(img))
            print(f"{name:16s} frame {frames - 1:3d} ({time.perf_counter() - t0:5.1f} s) -> {target}")
    shutil.rmtree(out / "__pycache__", ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
