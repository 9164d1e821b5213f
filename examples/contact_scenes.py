"""Contact scenes with km.contact (Incremental Potential Contact): intersection-free by
construction, with Coulomb friction.

    .venv/bin/python examples/contact_scenes.py --out demo_output/contact [--scene cloth|pile|stairs|all] [--small]

* cloth:  a square cloth falls on a sphere, drapes over it, and slides off a tilted box below;
* pile:   soft cubes dropped one above the other onto the ground, piling up;
* stairs: a jelly cube thrown down a flight of stairs.

Each scene prints one line per frame (Newton iterations, contact count, minimum distance, the
CCD's share of the time), checks after every step that no two primitives touch or cross
(exactly: min distance > 0, no edge through a triangle), and writes a PNG of its last frame.
``--small`` runs coarse meshes for a few frames (the smoke test).
"""

import argparse
import time
from pathlib import Path

import numpy as np

import kinema as km

G = (0.0, -9.81, 0.0)


def rotation_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def cloth_scene(small, n=None):
    n = n or (8 if small else 24)
    scene = km.contact.Scene(gravity=G, dhat=2e-3, friction=0.3)
    x, tri, springs = km.contact.cloth_mesh(n, n, 0.8, origin=(-0.4, 0.33, -0.4))
    scene.add_cloth(x, tri, springs=springs, stiffness=1500, density=0.2)
    scene.add_collider("sphere", center=(0, 0, 0), radius=0.3, subdivisions=2 if small else 3)
    v, t = km.contact.box_surface((-0.6, -0.5, -0.6), (0.6, -0.4, 0.6))
    scene.add_collider("mesh", vertices=v @ rotation_z(12).T, triangles=t)  # tilted: the cloth slides off
    return scene, 1 / 50


def pile_scene(small, count=None, n=None):
    count, n = count or (3 if small else 6), n or (1 if small else 2)
    scene = km.contact.Scene(gravity=G, dhat=1e-3, friction=0.4)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    rng = np.random.default_rng(1)
    for k in range(count):
        lo = np.array([rng.uniform(-0.04, 0.04), 0.02 + 0.12 * k, rng.uniform(-0.04, 0.04)])
        v, t = km.fem.box_mesh(lo, lo + 0.1, n)
        scene.add_solid(v, t, youngs_modulus=5e4, poisson_ratio=0.4, density=500)
    return scene, 1 / 100


def stairs_scene(small):
    scene = km.contact.Scene(gravity=G, dhat=1e-3, friction=0.3)
    verts, tris = [], []
    for k in range(4):  # four steps 0.1 m high and deep, going down along +x
        v, t = km.contact.box_surface((0.1 * k, -0.5, -0.3), (0.1 * k + 0.1, 0.4 - 0.1 * k, 0.3))
        tris.append(t + sum(len(w) for w in verts))
        verts.append(v)
    scene.add_collider("mesh", vertices=np.concatenate(verts), triangles=np.concatenate(tris))
    scene.add_collider("plane", point=(0, -0.5, 0), normal=(0, 1, 0))
    v, t = km.fem.box_mesh((0.0, 0.42, -0.04), (0.08, 0.5, 0.04), 1 if small else 3)
    jelly = scene.add_solid(v, t, youngs_modulus=2e4, poisson_ratio=0.45, density=1000)
    scene.v[jelly] = (1.0, 0.0, 0.0)
    return scene, 1 / 100


SCENES = {"cloth": cloth_scene, "pile": pile_scene, "stairs": stairs_scene}


def run(name, frames, small, out):
    scene, dt = SCENES[name](small)
    history = []
    start = time.perf_counter()
    for frame in range(frames):
        stats = scene.step(dt)
        d, hits = scene.min_distance(), scene.intersections()
        if not (d > 0) or hits:
            raise AssertionError(f"{name}: penetration at frame {frame}: min distance {d}, {hits}")
        history.append(stats)
        print(f"{name} frame {frame:3d}  t={stats.time:.3f}s  newton={stats.newton_iterations:3d}  "
              f"contacts={stats.contact_count:5d}  min_distance={stats.min_distance:.2e} m  "
              f"ccd={stats.ccd_share:.0%}  {stats.seconds:.2f}s")
    print(f"{name}: {frames} frames in {time.perf_counter() - start:.1f} s")
    if out is not None:
        draw(scene, out / f"contact_{name}.png", name)
    return scene, history


def draw(scene, path, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    x, faces = scene.x, scene.faces
    moving = scene.mass[faces].min(axis=1) > 0
    for mask, color, alpha in ((~moving, "0.7", 0.35), (moving, "tab:orange", 0.9)):
        tris = x[faces[mask]][:, :, [0, 2, 1]]  # y up on screen
        ax.add_collection3d(Poly3DCollection(tris, facecolor=color, edgecolor="k", linewidths=0.1, alpha=alpha))
    lo, hi = x[scene.mass > 0].min(0) - 0.3, x[scene.mass > 0].max(0) + 0.3
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[2], hi[2])
    ax.set_zlim(lo[1], hi[1])
    ax.set_box_aspect(tuple((hi - lo)[[0, 2, 1]]))  # equal scales: a sphere looks round
    ax.set_title(f"{title}, t = {scene.time:.2f} s")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("demo_output/contact"))
    parser.add_argument("--scene", choices=[*SCENES, "all"], default="all")
    parser.add_argument("--frames", type=int, default=None, help="steps per scene (default 100, 8 with --small)")
    parser.add_argument("--small", action="store_true", help="coarse meshes, few frames (smoke test)")
    args = parser.parse_args(argv)
    frames = args.frames or (8 if args.small else 100)
    names = list(SCENES) if args.scene == "all" else [args.scene]
    return {name: run(name, frames, args.small, args.out) for name in names}


if __name__ == "__main__":
    main()
