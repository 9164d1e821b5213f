"""A falling drop of SPH water, its free surface reconstructed every few frames (km.surface),
written as PLY beside a path-traced picture of it as water (absorbing dielectric).

    python examples/water_surface.py --out water [--frames 12 --spacing 0.02 --spp 16 --width 320]
    python examples/water_surface.py --out water --view      # the same run in the live viewer

Writes OUT/surface_NNN.ply (open in Blender or ParaView) and OUT/water.png (the last frame).
"""

import argparse
from pathlib import Path

import numpy as np

import kinema as km


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="water")
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--spacing", type=float, default=0.02)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--view", action="store_true", help="show the run in km.viewer instead (needs a display)")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s = args.spacing
    lower, upper = np.zeros(3), np.array([0.6, 0.6, 0.6])
    pool = km.sph.block([0, 0, 0], [0.6, 0.12, 0.6], s)
    drop = km.sph.block([0.2, 0.3, 0.2], [0.4, 0.5, 0.4], s)
    x = np.concatenate([pool, drop])
    fluid = km.sph.Fluid(x, s, gravity=(0, -9.81, 0), domain=(lower, upper), viscosity=1e-5)
    fps = 30

    def mesh():
        return km.surface.reconstruct(fluid.x, s)

    if args.view:
        from kinema.scenes.adapters.base import PointData

        def items():
            m = mesh()
            return [PointData("surface", m.vertices, surface=m.triangles)]
        km.viewer.view(km.viewer.CallbackSource(lambda: fluid.advance(1 / fps), items, name="water"))
        return
    for frame in range(1, args.frames + 1):
        fluid.advance(1 / fps)
        surface = mesh()
        surface.write(out / f"surface_{frame:03d}.ply")
        print(f"frame {frame:3d}  t = {fluid.time:.3f} s  {len(surface.triangles)} triangles, "
              f"volume {surface.volume():.4f} m^3 (particles {len(x) * s**3:.4f})", flush=True)
    scene = km.render.Scene()
    scene.add_mesh(surface.vertices, surface.triangles, km.render.dielectric(1.33, absorption=(6.0, 2.0, 0.8)))
    scene.add_plane((0, 0, 0), (0, 1, 0), km.render.lambertian(0.6))
    cam = km.render.Camera((1.1, 0.8, 1.4), (0.3, 0.15, 0.3), vfov=40, width=args.width,
                           height=round(0.75 * args.width))
    km.render.to_png(scene.render(cam, spp=args.spp), out / "water.png")
    print(f"-> {out / 'water.png'}")


if __name__ == "__main__":
    main()
