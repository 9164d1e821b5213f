"""A Cornell-box-like scene with the three materials, path traced to a PNG.

    python examples/render_spheres.py --out cornell.png [--width 320 --height 240 --spp 256]

A white box with a red left and a green right wall (infinite planes, open towards the camera),
an emissive panel under the ceiling (two triangles), and three spheres: diffuse (Lambertian),
brushed metal (fuzz 0.15) and glass (ior 1.5). The only light is the panel, found by BSDF
sampling alone, so the image needs a few hundred samples per pixel to lose its noise.
"""

import argparse
import time

import numpy as np

import kinema as km

R = km.render


def cornell_box() -> R.Scene:
    scene = R.Scene()
    white, red, green = R.lambertian(0.73), R.lambertian((0.65, 0.05, 0.05)), R.lambertian((0.12, 0.45, 0.15))
    scene.add_plane((0, 0, 0), (0, 1, 0), white)       # floor
    scene.add_plane((0, 2, 0), (0, -1, 0), white)      # ceiling
    scene.add_plane((0, 0, -1), (0, 0, 1), white)      # back wall
    scene.add_plane((-1, 0, 0), (1, 0, 0), red)        # left wall
    scene.add_plane((1, 0, 0), (-1, 0, 0), green)      # right wall
    panel = np.array([[-0.35, 1.999, -0.55], [0.35, 1.999, -0.55], [0.35, 1.999, 0.15], [-0.35, 1.999, 0.15]])
    scene.add_mesh(panel, [[0, 1, 2], [0, 2, 3]], R.emissive(12.0))
    scene.add_spheres([[-0.5, 0.35, -0.45]], 0.35, R.lambertian((0.8, 0.8, 0.3)))
    scene.add_spheres([[0.05, 0.3, 0.1]], 0.3, R.metal((0.9, 0.9, 0.9), fuzz=0.15))
    scene.add_spheres([[0.55, 0.32, -0.3]], 0.32, R.dielectric(1.5))
    return scene


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="cornell.png")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    scene = cornell_box()
    cam = R.Camera((0, 1, 3.4), (0, 0.9, 0), vfov=40, width=args.width, height=args.height)
    t0 = time.perf_counter()
    image = scene.render(cam, spp=args.spp, max_depth=12, seed=args.seed, sky=0.0)
    seconds = time.perf_counter() - t0
    R.to_png(image, args.out)
    s = scene.last_stats
    print(f"{args.out}: {args.width}x{args.height}, {args.spp} spp, {seconds:.2f} s, "
          f"{s['rays'] / max(s['seconds'], 1e-9) / 1e6:.2f} Mrays/s on {km.get_num_threads()} threads")


if __name__ == "__main__":
    main()
