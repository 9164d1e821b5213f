"""Deformable-body demonstration: a hanging cloth and a soft 3D body swinging from a fixed end.

    .venv/bin/python examples/cloth_and_beam.py --out demo_output/deform [--frames 90] [--no-video]

Writes, into the output folder:
  cloth/frame_NNNN.vtu   the cloth (km.massspring, implicit, 1/30 s steps) as a VTK triangle
                         mesh per frame (ParaView)
  cloth/frame_NNNN.obj   the same as Wavefront OBJ (Blender imports OBJ natively; a sequence
                         loads as an animation with a mesh-sequence add-on)
  body/frame_NNNN.vtu    the neo-Hookean beam (km.fem, implicit Newton) as a tetrahedral mesh
  body/frame_NNNN.obj    its boundary surface, outward-oriented triangles (km.mesh.surface)
  preview/NNNN.png, deform.mp4   a side-by-side preview (the video when ffmpeg is installed; not with --no-video)
  summary.txt            steps, Newton iterations and timings
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import kinema as km
from kinema.scenes.output import write_mp4


def cloth_scene(n):
    x, springs, kinds = km.massspring.cloth(n, n, 1.0, return_kinds=True)
    x[:, 2] = 1.0  # horizontal at z = 1, pinned at two corners of the y = 0 edge: it falls and swings
    stiffness = np.where(kinds == 2, 50.0, 2000.0)  # soft bending springs
    sys = km.massspring.System(x, springs, stiffness=stiffness, mass=0.2 / n**2, damping=0.02,
                               fixed=[0, (n - 1) * n], gravity=(0.0, 0.0, -9.81))
    I, J = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (I * n + J).ravel()
    tris = np.concatenate([np.stack([a, a + n, a + n + 1], 1), np.stack([a, a + n + 1, a + 1], 1)])
    return sys, tris


def body_scene(cells):
    V, T = km.fem.box_mesh([0, 0, 0], [1.0, 0.2, 0.2], (cells, max(cells // 5, 1), max(cells // 5, 1)))
    body = km.fem.Body(V, T, model="neohookean", youngs_modulus=2e5, poisson_ratio=0.4,
                       density=1000.0, fixed=np.flatnonzero(V[:, 0] < 1e-12),
                       gravity=(0.0, 0.0, -9.81), damping=0.5)
    return body, T


def render(path, cloth_x, tris, body_x, surface):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(9, 4.5), dpi=80)
    for k, (x, faces, title) in enumerate([(cloth_x, tris, "cloth (km.massspring)"),
                                           (body_x, surface, "soft beam (km.fem)")]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(x[faces], facecolor="tab:orange" if k else "tab:blue",
                                             edgecolor="k", linewidth=0.1, alpha=0.8))
        lo, hi = (-0.1, -0.2, -0.1), (1.1, 1.1, 1.1)
        if k:
            lo, hi = (-0.1, -0.6, -0.9), (1.1, 0.6, 0.3)
        ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
        ax.set_title(title)
        ax.view_init(elev=15, azim=-60)
    fig.savefig(path)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo_output/deform")
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--cloth", type=int, default=24, help="cloth vertices per side")
    parser.add_argument("--cells", type=int, default=10, help="beam cells along its length")
    parser.add_argument("--no-video", action="store_true")
    args = parser.parse_args(argv)
    out = Path(args.out)
    for sub in ("cloth", "body") + (() if args.no_video else ("preview",)):
        (out / sub).mkdir(parents=True, exist_ok=True)
    cloth, tris = cloth_scene(args.cloth)
    body, tets = body_scene(args.cells)
    surface = km.mesh.surface(body.x, tets)
    dt = 1 / 30
    newton, t_cloth, t_body = [], 0.0, 0.0
    for frame in range(args.frames):
        t = time.perf_counter()
        cloth.step(dt)
        t_cloth += time.perf_counter() - t
        t = time.perf_counter()
        newton.append(body.step(dt).iterations)
        t_body += time.perf_counter() - t
        km.io.write_mesh(out / "cloth" / f"frame_{frame:04d}.vtu", cloth.x, tris)
        km.io.write_mesh(out / "body" / f"frame_{frame:04d}.vtu", body.x, tets)
        km.io.write_mesh(out / "cloth" / f"frame_{frame:04d}.obj", cloth.x, tris)
        km.io.write_mesh(out / "body" / f"frame_{frame:04d}.obj", body.x, surface)
        if not args.no_video:
            render(out / "preview" / f"{frame:04d}.png", cloth.x, tris, body.x, surface)
    video = None
    if not args.no_video and write_mp4(out / "deform.mp4", out / "preview" / "%04d.png", 30):
        video = out / "deform.mp4"
    summary = (f"frames {args.frames}, dt {dt:.4f} s\n"
               f"cloth: {args.cloth}^2 vertices, {len(cloth.springs)} springs, implicit, "
               f"{t_cloth / args.frames * 1e3:.2f} ms/step\n"
               f"body: {len(body.x)} vertices, {len(tets)} tets, neo-Hookean, "
               f"{t_body / args.frames * 1e3:.2f} ms/step, Newton iterations mean "
               f"{np.mean(newton):.2f} max {max(newton)}\n"
               f"video: {video or 'not written'}\n")
    (out / "summary.txt").write_text(summary)
    print(summary, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
