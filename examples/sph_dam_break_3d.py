"""3D dam break hitting an obstacle with km.sph (DFSPH): particle files per frame and a preview.

    python examples/sph_dam_break_3d.py --out out/dambreak [--spacing 0.02] [--frames 60] [--fps 30]

Writes per frame OUT/frame_0000.ply ... (binary little-endian PLY point clouds: x, y, z and the
speed per vertex; Blender imports them, ParaView opens them too) and OUT/frame_0000.vtk ...
(legacy binary VTK polydata with one vertex cell per particle and a "speed" array: ParaView
renders them directly and reads the numbered files as one time series), OUT/obstacle.ply and
OUT/obstacle.vtk (the obstacle's boundary samples) and OUT/preview.mp4 (a side view coloured by
speed, rendered with matplotlib and encoded by ffmpeg when both are available).
"""

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km


def write_ply(path, x, speed=None):
    """Binary PLY point cloud: float32 x, y, z (and speed)."""
    n = len(x)
    props = ["x", "y", "z"] + (["speed"] if speed is not None else [])
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    cols = [x.astype("<f4")] + ([speed.astype("<f4")[:, None]] if speed is not None else [])
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(np.hstack(cols)).tobytes())


def write_vtk(path, x, speed=None):
    """Legacy binary VTK polydata (big-endian): the points, one VERTICES cell each, and speed."""
    n = len(x)
    with open(path, "wb") as f:
        f.write(b"# vtk DataFile Version 3.0\nkinema sph particles\nBINARY\nDATASET POLYDATA\n")
        f.write(b"POINTS %d float\n" % n)
        f.write(np.ascontiguousarray(x, dtype=">f4").tobytes())
        cells = np.empty((n, 2), dtype=">i4")
        cells[:, 0] = 1
        cells[:, 1] = np.arange(n)
        f.write(b"\nVERTICES %d %d\n" % (n, 2 * n))
        f.write(cells.tobytes())
        if speed is not None:
            f.write(b"\nPOINT_DATA %d\nSCALARS speed float 1\nLOOKUP_TABLE default\n" % n)
            f.write(np.ascontiguousarray(speed, dtype=">f4").tobytes())
        f.write(b"\n")


def scene(spacing):
    tank = ([0.0, 0.0, 0.0], [1.6, 0.8, 0.6])
    water = km.sph.block([0.0, 0.0, 0.0], [0.4, 0.6, 0.6], spacing)
    obstacle = km.sph.block([0.9, 0.0, 0.24], [1.02, 0.3, 0.36], spacing)
    return water, obstacle, tank


def render(path, x, speed, tank):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    order = np.argsort(x[:, 2])  # back to front along z
    ax.scatter(x[order, 0], x[order, 1], c=speed[order], s=1.5, cmap="viridis", vmin=0, vmax=3)
    ax.add_patch(plt.Rectangle((0.9, 0.0), 0.12, 0.3, color="0.4"))
    ax.set_xlim(tank[0][0], tank[1][0])
    ax.set_ylim(tank[0][1], tank[1][1])
    ax.set_aspect("equal")
    ax.set_axis_off()
    fig.savefig(path, bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/dambreak")
    p.add_argument("--spacing", type=float, default=0.02)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--method", default="dfsph", choices=km.sph.METHODS)
    p.add_argument("--no-video", action="store_true")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    water, obstacle, tank = scene(args.spacing)
    fluid = km.sph.Fluid(water, args.spacing, method=args.method, gravity=(0, -9.81, 0), domain=tank,
                         boundary=obstacle, viscosity=1e-5)
    write_ply(out / "obstacle.ply", obstacle)
    write_vtk(out / "obstacle.vtk", obstacle)
    video = not args.no_video and shutil.which("ffmpeg") is not None
    print(f"{fluid.n} particles, {fluid.boundary_count} boundary samples, {args.frames} frames")
    t0 = time.perf_counter()
    for frame in range(args.frames + 1):
        if frame:
            steps = fluid.advance(1.0 / args.fps)
            print(f"frame {frame:4d}  t = {fluid.time:.3f} s  steps {steps:3d}  "
                  f"density error {fluid.density_error():.1e}  wall {time.perf_counter() - t0:.1f} s")
        speed = np.linalg.norm(fluid.v, axis=1)
        write_ply(out / f"frame_{frame:04d}.ply", fluid.x, speed)
        write_vtk(out / f"frame_{frame:04d}.vtk", fluid.x, speed)
        if video:
            render(out / f"frame_{frame:04d}.png", fluid.x, speed, tank)
    if video:
        subprocess.run(["ffmpeg", "-y", "-loglevel", "error", "-framerate", str(args.fps), "-i",
                        str(out / "frame_%04d.png"), "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
                        "-pix_fmt", "yuv420p", str(out / "preview.mp4")], check=True)
        for png in out.glob("frame_*.png"):
            png.unlink()
        print(f"preview: {out / 'preview.mp4'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
