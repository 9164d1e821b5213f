"""Two Plummer spheres ("galaxies") on a parabolic orbit collide and merge (km.nbody).

    .venv/bin/python examples/galaxy_collision.py --out demo_output/galaxies [--particles 5000] [--duration 40]

Each sphere: total mass 1, Plummer radius 1 (G = 1), softening 0.05; the centres start 10 apart
with the relative speed of a parabolic (zero-energy) two-point-mass orbit of pericentre 1.
Forces by the 3D FMM (eps 1e-6), kick-drift-kick leapfrog. Writes frames (x-y projection,
coloured by galaxy), galaxy_collision.mp4 (ffmpeg, when installed) and energy_error.png, the
relative energy error |E(t)/E(0) - 1| over the run, and prints it.
"""

import argparse
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

import kinema as km


def initial_conditions(n, separation=10.0, pericentre=1.0, G=1.0):
    """Two unit-mass Plummer spheres on the parabolic orbit of two point masses of mass 1:
    relative speed sqrt(2 G M / r) at separation r, angular momentum sqrt(2 G M q) for
    pericentre q (M = 2)."""
    xa, va, ma = km.nbody.plummer(n, seed=1, G=G)
    xb, vb, mb = km.nbody.plummer(n, seed=2, G=G)
    M = 2.0
    v = np.sqrt(2 * G * M / separation)
    h = np.sqrt(2 * G * M * pericentre)
    vt = h / separation  # transverse part
    vr = -np.sqrt(max(v**2 - vt**2, 0.0))  # approaching
    rel_x = np.array([separation, 0.0, 0.0])
    rel_v = np.array([vr, vt, 0.0])
    x = np.r_[xa - 0.5 * rel_x, xb + 0.5 * rel_x]
    vel = np.r_[va - 0.5 * rel_v, vb + 0.5 * rel_v]
    return x, vel, np.r_[ma, mb]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/galaxies"))
    parser.add_argument("--particles", type=int, default=5000, help="per galaxy")
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--dt", type=float, default=0.02)
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, v, m = initial_conditions(args.particles)
    sim = km.nbody.System(x, v, m, softening=0.05, eps=1e-6)
    e0 = sim.energy()
    frames = args.out / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    colour = np.r_[np.zeros(args.particles), np.ones(args.particles)]
    times, errors = [0.0], [0.0]
    fig, ax = plt.subplots(figsize=(6, 6), facecolor="black")
    start = time.perf_counter()
    for k in range(args.frames + 1):
        ax.clear()
        ax.set_facecolor("black")
        ax.scatter(sim.x[:, 0], sim.x[:, 1], c=colour, s=2.0, cmap="coolwarm", alpha=0.8, linewidths=0)
        ax.set_xlim(-8, 8)
        ax.set_ylim(-8, 8)
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(f"t = {sim.time:5.1f}   N = {len(m)}", color="white")
        fig.savefig(frames / f"frame_{k:04d}.png", dpi=100, facecolor="black")
        if k < args.frames:
            sim.advance(args.duration / args.frames, args.dt)
            times.append(sim.time)
            errors.append(abs(sim.energy() / e0 - 1))
            if k % 10 == 0:
                print(f"t = {sim.time:6.2f}  |dE/E| = {errors[-1]:.2e}  ({time.perf_counter() - start:.0f} s)",
                      flush=True)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(times[1:], errors[1:])
    ax.set_xlabel("t")
    ax.set_ylabel("|E(t) / E(0) - 1|")
    ax.set_title(f"galaxy collision: energy error (leapfrog, dt = {args.dt}, FMM eps 1e-6)")
    fig.tight_layout()
    fig.savefig(args.out / "energy_error.png", dpi=120)
    plt.close(fig)
    print(f"final relative energy error {errors[-1]:.2e}, largest {max(errors):.2e}")
    if shutil.which("ffmpeg"):
        video = args.out / "galaxy_collision.mp4"
        subprocess.run(["ffmpeg", "-y", "-loglevel", "error", "-framerate", "20", "-i",
                        str(frames / "frame_%04d.png"), "-pix_fmt", "yuv420p", "-vf",
                        "scale=trunc(iw/2)*2:trunc(ih/2)*2", str(video)], check=True)
        print(f"video: {video}")
    return max(errors)


if __name__ == "__main__":
    main()
