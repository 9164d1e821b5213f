"""Two co-rotating vortex patches merging, by the vortex-particle method on km.fmm.

    .venv/bin/python examples/vortex_merger.py --out demo_output/vortex [--particles 4000] [--steps 200]

Writes frames (PNG, particles coloured by circulation) and vortex_merger.mp4 (ffmpeg, when
installed), and prints the drift of the total circulation and of the linear impulse.
"""

import argparse
import shutil
import subprocess
from pathlib import Path

import numpy as np

import kinema as km
from kinema.vortex import VortexParticles, merging_patches


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/vortex"))
    parser.add_argument("--particles", type=int, default=4000, help="particles per patch")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--dt", type=float, default=0.05)
    parser.add_argument("--every", type=int, default=2, help="steps between frames")
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, gamma, core = merging_patches(args.particles)
    sim = VortexParticles(x, gamma, core, eps=1e-8)
    frames = args.out / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    c0, i0 = sim.total_circulation(), sim.linear_impulse()
    fig, ax = plt.subplots(figsize=(6, 6))
    for step in range(args.steps + 1):
        if step % args.every == 0:
            ax.clear()
            ax.scatter(sim.x[:, 0], sim.x[:, 1], c=sim.circulation, s=1, cmap="viridis")
            ax.set_xlim(-1.2, 1.2)
            ax.set_ylim(-1.2, 1.2)
            ax.set_aspect("equal")
            ax.set_title(f"vortex merger, t = {sim.time:.2f}, {len(sim.x)} particles")
            fig.savefig(frames / f"frame_{step // args.every:04d}.png", dpi=100)
        if step < args.steps:
            sim.step(args.dt)
    plt.close(fig)
    dc = abs(sim.total_circulation() - c0)
    di = np.linalg.norm(sim.linear_impulse() - i0)
    print(f"t = {sim.time:.2f}: circulation drift {dc:.2e}, linear impulse drift {di:.2e}")
    if shutil.which("ffmpeg"):
        video = args.out / "vortex_merger.mp4"
        subprocess.run(["ffmpeg", "-y", "-loglevel", "error", "-framerate", "25", "-i",
                        str(frames / "frame_%04d.png"), "-pix_fmt", "yuv420p", "-vf",
                        "scale=trunc(iw/2)*2:trunc(ih/2)*2", str(video)], check=True)
        print(f"video: {video}")


if __name__ == "__main__":
    main()
