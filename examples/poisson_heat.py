"""kinema's numerical demonstration: fields solved, checked and written to disk.

    .venv/bin/python examples/poisson_heat.py --out demo_output/numerics [--frames 96] [--size 256]

scripts/demo.sh runs it after the smoke_plume scene.

Writes, into the output folder:
  poisson_potential.png   a 2D Poisson solution around an insulating obstacle (mgpcg)
  heat/frame_NNNN.png     frames of heat diffusing through a box with an insulating wall
  heat.mp4                the frames as a video (when ffmpeg is installed)
  heat_final.npz, .vti    the final temperature field (NumPy and VTK image data for ParaView)
  work_precision.csv/.png wall time against error for every Poisson method and grid size
  summary.txt             what was run, with the measured errors and times
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

import kinema as km
from kinema.scenes.output import write_mp4, write_png
from kinema.scenes.preview import field_image


def log(msg):
    print(f"[kinema demo] {msg}", flush=True)


def save_image(path, field, cmap, vmin=None, vmax=None, mask=None):
    """A cell field [i, j] (x right, y up) as a PNG; ``mask`` cells grey."""
    write_png(path, field_image(field, cmap=cmap, vmin=vmin, vmax=vmax, mask=mask))


def poisson_obstacle(out, n):
    """Potential flow past a disk: -lap(phi) = 0 with a source and a sink, Neumann walls."""
    h = 1.0 / n
    X, Y = np.meshgrid((np.arange(2 * n) + 0.5) * h, (np.arange(n) + 0.5) * h, indexing="ij")
    solid = (X - 1.0) ** 2 + (Y - 0.5) ** 2 < 0.15**2
    f = np.exp(-((X - 0.25) ** 2 + (Y - 0.5) ** 2) / 0.002) - np.exp(-((X - 1.75) ** 2 + (Y - 0.5) ** 2) / 0.002)
    f[solid] = 0
    f[~solid] -= f[~solid].mean()
    t0 = time.perf_counter()
    phi, info = km.poisson.solve(f, h, "neumann", "mgpcg", tol=1e-10, solid=solid)
    seconds = time.perf_counter() - t0
    residual = f - km.poisson.laplacian(phi, h, "neumann", solid)
    check = np.abs(residual[~solid]).max() / np.abs(f).max()
    save_image(out / "poisson_potential.png", phi, "RdBu_r", mask=solid)
    np.savez_compressed(out / "poisson_potential.npz", phi=phi, solid=solid, h=h)
    log(f"Poisson {phi.shape}: {info.iterations} MGPCG iterations, residual {info.residual:.2e}, "
        f"{seconds:.3f} s")
    return f"poisson {phi.shape} mgpcg: iterations={info.iterations} residual={info.residual:.2e} " \
           f"max|f - A phi|/max|f|={check:.2e} seconds={seconds:.3f}"


def heat_movie(out, n, frames):
    """Heat from two hot spots spreading through a box split by a wall with a gap."""
    h, kappa = 1.0 / n, 1e-3
    shape = (n, n)
    X, Y = np.meshgrid((np.arange(n) + 0.5) * h, (np.arange(n) + 0.5) * h, indexing="ij")
    solid = (np.abs(X - 0.5) < 0.02) & ~(np.abs(Y - 0.5) < 0.08)
    T = np.where(((X - 0.25) ** 2 + (Y - 0.3) ** 2 < 0.01) | ((X - 0.2) ** 2 + (Y - 0.75) ** 2 < 0.005), 1.0, 0.0)
    T[solid] = 0
    heat0 = T.sum()
    dt = 0.12  # 96 frames of 4 steps: a diffusion length sqrt(2 kappa t) of ~0.3
    stepper = km.diffusion.Stepper(shape, kappa, dt, h, "crank_nicolson", "neumann", solid=solid)
    frame_dir = out / "heat"
    frame_dir.mkdir(exist_ok=True)
    t_start = time.perf_counter()
    for frame in range(frames):
        save_image(frame_dir / f"frame_{frame:04d}.png", T, "inferno", 0.0, 0.35, mask=solid)
        T = stepper.step(T, steps=4)
        if frame % 10 == 0 or frame == frames - 1:
            rate = (frame + 1) / (time.perf_counter() - t_start)
            log(f"heat frame {frame + 1}/{frames}  t = {(frame + 1) * 4 * dt:.0f} s  "
                f"{rate:.1f} frames/s  ETA {(frames - frame - 1) / rate:.0f} s")
    drift = abs(T.sum() - heat0) / heat0
    np.savez_compressed(out / "heat_final.npz", T=T, solid=solid, h=h, kappa=kappa)
    km.io.write_grid(out / "heat_final.vti", {"temperature": T}, h)
    video = "not written (ffmpeg not found)"
    if write_mp4(out / "heat.mp4", frame_dir / "frame_%04d.png", 24):
        video = str(out / "heat.mp4")
    log(f"heat: {frames} frames, relative heat drift {drift:.1e}, video {video}")
    return f"heat {shape} crank_nicolson: frames={frames} relative_heat_drift={drift:.2e} video={video}"


def work_precision(out, sizes):
    """Time against error to the manufactured solution, per method and grid size."""
    rows = []
    for n in sizes:
        h = 1.0 / n
        X, Y = np.meshgrid((np.arange(n) + 0.5) * h, (np.arange(n) + 0.5) * h, indexing="ij")
        exact = np.sin(np.pi * X) * np.sin(np.pi * Y)
        f = 2 * np.pi**2 * exact
        for method in km.poisson.METHODS:
            if method in ("jacobi", "gauss_seidel") and n > 64:
                continue  # O(n^2) iterations: minutes at larger sizes
            if method == "cg" and n > 512:
                continue
            t0 = time.perf_counter()
            u, info = km.poisson.solve(f, h, method=method, tol=1e-10)
            seconds = time.perf_counter() - t0
            err = float(np.abs(u - exact).max())
            rows.append(dict(method=method, n=n, seconds=seconds, error=err, iterations=info.iterations,
                             threads=km.get_num_threads()))
            log(f"work-precision {method:>12} {n:5d}^2: {seconds:8.4f} s  error {err:.2e}")
    with open(out / "work_precision.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for method in km.poisson.METHODS:
        pts = [(r["seconds"], r["error"]) for r in rows if r["method"] == method]
        if pts:
            ax.loglog(*zip(*pts), "o-", label=method)
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("max error vs exact solution")
    ax.set_title(f"2D Poisson, tol 1e-10, {km.get_num_threads()} thread(s)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "work_precision.png", dpi=120)
    plt.close(fig)
    return [f"work_precision {r['method']} n={r['n']}: seconds={r['seconds']:.4f} error={r['error']:.2e}" for r in rows]


def main(argv=None):
    parser = argparse.ArgumentParser(prog="examples/poisson_heat.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="demo_output", help="output folder (created)")
    parser.add_argument("--frames", type=int, default=96, help="heat video frames")
    parser.add_argument("--size", type=int, default=256, help="grid cells per unit length")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128, 256, 512, 1024],
                        help="grid sizes of the work-precision study")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.size < 8 or min(args.sizes) < 8:
        parser.error("--frames must be >= 1, --size and --sizes >= 8")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log(f"kinema {km.__version__}, {km.get_num_threads()} thread(s), BLAS {km.build_info()['blas']}")
    lines = [poisson_obstacle(out, args.size), heat_movie(out, args.size, args.frames)]
    lines += work_precision(out, args.sizes)
    (out / "summary.txt").write_text("\n".join(lines) + "\n")
    log(f"done: outputs in {out.resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
