"""km.render benchmarks: path-tracing throughput (rays per second) and BVH build time against
scene size, and the preview's frame time at simulation sizes.

    python bench/render/render_bench.py            # spheres 1e3 .. 1e6, a 131k-triangle mesh, previews
    python bench/render/render_bench.py --quick    # spheres 1e3 .. 1e5, a small mesh (wiring check)

Scenes: n particles of radius 0.35 (1/n)^(1/3) uniform in the unit cube above a floor plane
(Lambertian albedo 0.7, gradient sky), or a torus mesh (metal, fuzz 0.2) above the floor.
Path tracing at 160x120, 4 spp, max_depth 8; rays/s counts closest-hit queries (camera rays and
bounces); per CPU-second (all threads' CPU time) it is less sensitive to the machine's load.
Preview at 640x480. Each figure is timed by bench/common/harness.py, which records the load
other processes put on the machine (other_load, cores) and retries disturbed runs. Checks before
recording: BVH against brute force on 300 rays, a finite image with mean radiance inside the
sky's range, and the preview's visible primitives equal to the tracer's primary hits.
CSV: bench/out/render.csv.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "common"))  # harness.py
import harness  # noqa: E402

import kinema as km  # noqa: E402

R = km.render
OUT = Path(__file__).resolve().parents[1] / "out"
SKY = ((1.0, 1.0, 1.0), (0.5, 0.7, 1.0))
CAM = dict(look_from=(0.5, 1.2, 2.6), look_at=(0.5, 0.4, 0.5), vfov=40)


def check(name, ok, detail):
    if not ok:
        raise AssertionError(f"{name}: result check failed ({detail}); not recording a time")


def particles(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (n, 3)), 0.35 * n ** (-1 / 3)


def particle_scene(n):
    x, r = particles(n)
    scene = R.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(0.6))
    scene.add_spheres(x, r, R.lambertian(0.7))
    return scene


def torus(major=0.35, minor=0.12, nu=512, nv=128):
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    x = np.stack([(major + minor * np.cos(V)) * np.cos(U) + 0.5, minor * np.sin(V) + 0.4,
                  (major + minor * np.cos(V)) * np.sin(U) + 0.5], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return x, tris


def mesh_scene(nu, nv):
    x, t = torus(nu=nu, nv=nv)
    scene = R.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(0.6))
    scene.add_mesh(x, t, R.metal(0.9, fuzz=0.2))
    return scene, len(t)


def check_bvh(scene, name):
    rng = np.random.default_rng(1)
    o = rng.uniform(-1, 2, (300, 3)) + np.array([0, 1.5, 0])
    d = rng.uniform(0, 1, (300, 3)) - o
    t1, i1 = scene.intersect(o, d)
    t2, i2 = scene.intersect(o, d, brute_force=True)
    check(name, np.array_equal(i1, i2) and np.array_equal(t1, t2), "BVH differs from brute force")


def bench_trace(rec, name, size, make_scene, rows):
    """make_scene() -> a new Scene; its BVH is built by the first query (timed on its own)."""
    cam = R.Camera(width=160, height=120, **CAM)
    tiny = R.Camera(width=1, height=1, **CAM)

    def build():
        s = make_scene()
        s.render(tiny, spp=1, max_depth=1)
        return s

    m_build = harness.measure(build, figure=lambda s, wall: s.last_stats["bvh_seconds"], max_tries=2)
    scene = m_build.value
    bvh = dict(scene.last_stats)
    check_bvh(scene, name)

    def trace():
        cpu0 = time.process_time()
        img = scene.render(cam, spp=4, max_depth=8, sky=SKY, seed=1)
        return img, dict(scene.last_stats), time.process_time() - cpu0

    m = harness.measure(trace, figure=lambda v, wall: v[1]["seconds"], max_tries=3)
    img, stats, cpu = m.value
    check(name, np.isfinite(img).all() and 0 < img.mean() <= 1.0, f"image mean {img.mean()}")
    rays_per_s, rays_per_cpu_s = stats["rays"] / stats["seconds"], stats["rays"] / cpu
    rec.record(f"{name}-trace", size, m.seconds, iterations=stats["rays"], measurement=m,
               notes={"mrays_per_s": f"{rays_per_s / 1e6:.3f}",
                      "mrays_per_cpu_s": f"{rays_per_cpu_s / 1e6:.3f}",
                      "bvh_nodes": bvh["bvh_nodes"], "bvh_depth": bvh["bvh_depth"]})
    rec.record(f"{name}-bvh-build", size, m_build.seconds, measurement=m_build)
    rows.append((name, size, rays_per_s / 1e6, rays_per_cpu_s / 1e6, m_build.seconds, bvh["bvh_depth"],
                 m.other_load, m_build.other_load))
    print(f"{name:10s} {size:>9d}  {rays_per_s / 1e6:7.3f} Mrays/s ({rays_per_cpu_s / 1e6:.3f} per CPU s)"
          f"  BVH {m_build.seconds:7.3f} s (depth {bvh['bvh_depth']})  load {m.other_load:.2f}/"
          f"{m_build.other_load:.2f}", flush=True)


def bench_preview(rec, n, rows):
    x, r = particles(n)
    cam = R.Camera(width=640, height=480, **CAM)
    scene = R.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(0.6))
    scene.add_spheres(x, r, R.lambertian(0.7))
    _, ids, _ = scene.preview(cam, return_ids=True)
    if n <= 100_000:
        check("preview", np.array_equal(ids, scene.primary_hits(cam)), "differs from primary hits")
    m = harness.measure(lambda: scene.preview(cam, sky=SKY), min_of=3, max_tries=6, warmup=True)
    check("preview", np.isfinite(m.value).all(), "non-finite pixel")

    def frame():  # what a simulation loop pays per frame: a new scene from the positions
        s = R.Scene()
        s.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(0.6))
        s.add_spheres(x, r, R.lambertian(0.7))
        return s.preview(cam, sky=SKY)

    m_frame = harness.measure(frame, min_of=3, max_tries=6)
    rec.record("preview-640x480", n, m.seconds, measurement=m)
    rec.record("preview-640x480-with-scene", n, m_frame.seconds, measurement=m_frame)
    rows.append((n, m.seconds, m_frame.seconds, m.other_load, m_frame.other_load))
    print(f"preview {n:>9d}  {1e3 * m.seconds:8.2f} ms  (+scene {1e3 * m_frame.seconds:8.2f} ms)  "
          f"load {m.other_load:.2f}/{m_frame.other_load:.2f}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    sizes = [1_000, 10_000, 100_000] if args.quick else [1_000, 10_000, 100_000, 1_000_000]
    rec = harness.Recorder(OUT / "render.csv", "render")
    print(f"threads {km.get_num_threads()}, commit {rec.commit}")
    trace_rows, preview_rows = [], []
    for n in sizes:
        bench_trace(rec, "spheres", n, lambda: particle_scene(n), trace_rows)
    nu, nv = (128, 32) if args.quick else (512, 128)
    bench_trace(rec, "torus-mesh", 2 * nu * nv, lambda: mesh_scene(nu, nv)[0], trace_rows)
    for n in sizes[-2:]:
        bench_preview(rec, n, preview_rows)
    print("\n| scene | primitives | Mrays/s (wall) | Mrays per CPU-s | BVH build [s] | BVH depth | "
          "other_load (trace/build) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | --- |")
    for name, n, mr, mc, b, depth, l1, l2 in trace_rows:
        print(f"| {name} | {n:,} | {mr:.2f} | {mc:.2f} | {b:.3f} | {depth} | {l1:.2f} / {l2:.2f} |")
    print("\n| particles | preview [ms] | scene + preview [ms] | other_load |")
    print("| ---: | ---: | ---: | --- |")
    for n, s, f, l1, l2 in preview_rows:
        print(f"| {n:,} | {1e3 * s:.1f} | {1e3 * f:.1f} | {l1:.2f} / {l2:.2f} |")


if __name__ == "__main__":
    main()
