"""km.render: the path tracer against analytic radiance, BVH against brute force, preview against
the tracer's primary hits, determinism, and argument checking.

Monte Carlo tolerances: the tracer returns the variance of every pixel's mean; pixels are
independent, so the image mean has standard error sqrt(sum var) / n_pixels, and estimates are
required within 5 of those.
"""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kinema as km

R = km.render
SIGMAS = 5.0


def camera_rays(cam, sx, sy):
    """Unit directions of the rays through image points (col + sx, row + sy), (h, w, 3): the
    pinhole model written out independently of the C++ code."""
    eye, at, up = (np.asarray(v, float) for v in (cam.look_from, cam.look_at, cam.up))
    w = (eye - at) / np.linalg.norm(eye - at)
    u = np.cross(up, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    h = math.tan(math.radians(cam.vfov) / 2)
    aspect = cam.width / cam.height
    x = (np.arange(cam.width) + sx) / cam.width
    y = (np.arange(cam.height) + sy) / cam.height
    X, Y = np.meshgrid(x, y)
    d = -w + ((2 * X - 1) * aspect * h)[..., None] * u + ((1 - 2 * Y) * h)[..., None] * v
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def sphere_pixel_classes(cam, center, radius):
    """+1 for pixels whose whole footprint sees the sphere, -1 for those that cannot see it, 0 on
    the silhouette. The cone of rays meeting the sphere has half-angle asin(r / D); the angle
    between a ray and the axis of the cone is quasi-convex on the image plane, so the largest
    angle between a pixel's centre ray and any ray through the pixel is at a corner."""
    to_c = np.asarray(center, float) - np.asarray(cam.look_from, float)
    dist = np.linalg.norm(to_c)
    alpha = math.asin(radius / dist)
    axis = to_c / dist
    centre = camera_rays(cam, 0.5, 0.5)
    ang = np.arccos(np.clip(centre @ axis, -1, 1))
    spread = np.zeros(ang.shape)
    for sx in (0.0, 1.0):
        for sy in (0.0, 1.0):
            corner = camera_rays(cam, sx, sy)
            spread = np.maximum(spread, np.arccos(np.clip(np.sum(corner * centre, -1), -1, 1)))
    margin = 1e-9
    cls = np.zeros(ang.shape, int)
    cls[ang + spread < alpha - margin] = 1
    cls[ang - spread > alpha + margin] = -1
    return cls


def mean_and_error(image, var):
    """Mean of an image (per channel) and its Monte Carlo standard error."""
    n = image.shape[0] * image.shape[1]
    return image.mean(axis=(0, 1)), np.sqrt(var.sum(axis=(0, 1))) / n


def assert_within(measured, expected, error, what):
    dev = np.abs(np.asarray(measured) - np.asarray(expected))
    bound = SIGMAS * np.asarray(error) + 1e-12 * np.abs(expected)
    assert np.all(dev <= bound), f"{what}: measured {measured}, expected {expected}, |diff| {dev} > bound {bound}"


SPHERE_CAM = R.Camera((0, 0, 4), (0, 0, 0), vfov=30, width=48, height=36)


# ------------------------------------------------------------------ furnace and energy


@pytest.mark.parametrize("albedo", [1.0, 0.6])
def test_furnace_convex_lambertian_sphere(albedo):
    """A convex object reflects each ray once and the ray escapes: a Lambertian sphere of albedo a
    in a uniform sky L shows exactly a L where it covers the whole pixel, L off it."""
    L = np.array([0.7, 1.0, 1.3])
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.lambertian(albedo))
    img = scene.render(SPHERE_CAM, spp=8, sky=L, max_depth=8)
    cls = sphere_pixel_classes(SPHERE_CAM, (0, 0, 0), 1.0)
    assert (cls == 1).sum() > 300 and (cls == -1).sum() > 300
    np.testing.assert_allclose(img[cls == 1], np.broadcast_to(albedo * L, img[cls == 1].shape), rtol=1e-12)
    np.testing.assert_allclose(img[cls == -1], np.broadcast_to(L, img[cls == -1].shape), rtol=1e-12)
    lo, hi = albedo * L * (1 - 1e-12), L * (1 + 1e-12)
    assert np.all(img >= lo) and np.all(img <= hi)


def test_white_furnace_nonconvex_cluster():
    """White furnace: albedo-1 surfaces in a uniform sky L are invisible, however often a path
    bounces between them (overlapping spheres and a mesh form concave pockets)."""
    rng = np.random.default_rng(3)
    scene = R.Scene()
    scene.add_spheres(rng.uniform(-0.5, 0.5, (20, 3)), rng.uniform(0.25, 0.5, 20), R.lambertian(1.0))
    scene.add_mesh([[-1, -1, -0.3], [1, -1, -0.3], [0, 1, 0.4]], [[0, 1, 2]], R.lambertian(1.0))
    cam = R.Camera((0, 0, 2.5), (0, 0, 0), vfov=40, width=48, height=36)
    img = scene.render(cam, spp=4, sky=2.0, max_depth=400)
    dev = np.abs(img - 2.0).max()
    assert dev <= 1e-12 * 2.0, f"white furnace: max |pixel - L| = {dev}"
    # Each path casts 1 + (bounces) rays; a convex scene would give exactly one bounce per path
    # that hits something. Here some paths bounce between the surfaces.
    paths = cam.width * cam.height * 4
    hit_fraction = (scene.primary_hits(cam) >= 0).mean()
    bounces_per_hit_path = (scene.last_stats["rays"] / paths - 1) / hit_fraction
    assert hit_fraction > 0.5 and bounces_per_hit_path > 1.02, (hit_fraction, bounces_per_hit_path)


def enclosure(albedo, emission):
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.lambertian(albedo, emission=emission))
    cam = R.Camera((0, 0, 0.2), (0, 0, -1), vfov=60, width=24, height=16)
    return scene, cam


def test_enclosure_geometric_series_exact_without_roulette():
    """Inside a closed Lambertian sphere of albedo a emitting E every bounce hits the sphere
    again: with D bounces and no roulette each path carries E (1 - a^D) / (1 - a) exactly."""
    a, E, D = 0.5, 1.5, 7
    scene, cam = enclosure(a, E)
    img = scene.render(cam, spp=2, max_depth=D, russian_roulette=False, sky=0.0)
    expected = E * (1 - a**D) / (1 - a)
    np.testing.assert_allclose(img, expected, rtol=1e-13)


def test_enclosure_with_roulette_converges_to_infinite_bounce_value():
    """Furnace with Russian roulette: the infinite-bounce radiance E / (1 - a) within the MC error
    (roulette terminates the paths, max_depth is far beyond where they end)."""
    a, E = 0.7, 1.0
    scene, cam = enclosure(a, E)
    img, var = scene.render(cam, spp=64, max_depth=1000, roulette_depth=1, sky=0.0, return_variance=True)
    mean, err = mean_and_error(img, var)
    assert np.all(err > 0)
    assert_within(mean, np.full(3, E / (1 - a)), err, "enclosure with roulette")
    # Paths average 1 / (1 - a) bounces: roulette cut them long before max_depth.
    rays_per_path = scene.last_stats["rays"] / (cam.width * cam.height * 64)
    assert abs(rays_per_path - 1 / (1 - a)) < 0.2, rays_per_path


def test_russian_roulette_is_unbiased():
    """Mean with roulette from the 2nd bounce equals the exact no-roulette value at the same
    max_depth, within the MC error; roulette ends paths early (fewer rays)."""
    a, E, D = 0.8, 1.0, 12
    scene, cam = enclosure(a, E)
    exact = scene.render(cam, spp=2, max_depth=D, russian_roulette=False, sky=0.0)
    rays_exact = scene.last_stats["rays"] / 2
    img, var = scene.render(cam, spp=64, max_depth=D, roulette_depth=2, sky=0.0, seed=11,
                            return_variance=True)
    rays_rr = scene.last_stats["rays"] / 64
    mean, err = mean_and_error(img, var)
    assert_within(mean, exact.mean(axis=(0, 1)), err, "roulette vs exact")
    assert rays_rr < 0.8 * rays_exact


def test_lambertian_plane_under_gradient_sky():
    """A Lambertian plane of albedo a with unit normal n under the sky L(d) = b + (t - b)(1 + d_y)/2
    reflects a (b + (t - b)(1 + 2 n_y / 3) / 2): the cosine-weighted mean of d is 2n/3. Under a
    uniform sky (t = b) this is a L with zero variance."""
    n = np.array([0.6, 0.8, 0.0])
    albedo = np.array([0.9, 0.5, 0.2])
    bottom, top = np.array([1.0, 0.2, 0.0]), np.array([0.2, 1.0, 3.0])
    scene = R.Scene()
    scene.add_plane((0, 0, 0), n, R.lambertian(albedo))
    cam = R.Camera(n * 2, (0, 0, 0), up=(0, 0, 1), vfov=50, width=24, height=24)
    img, var = scene.render(cam, spp=32, sky=(bottom, top), return_variance=True, seed=5)
    assert (scene.primary_hits(cam) == 0).all()  # the plane fills the picture
    mean, err = mean_and_error(img, var)
    expected = albedo * (bottom + (top - bottom) * (1 + 2 * n[1] / 3) / 2)
    assert_within(mean, expected, err, "Lambertian plane, gradient sky")
    uniform = scene.render(cam, spp=4, sky=1.7)
    np.testing.assert_allclose(uniform, np.broadcast_to(1.7 * albedo, uniform.shape), rtol=1e-12)


def test_metal_energy():
    """A perfect mirror (albedo 1, fuzz 0) sphere in a uniform sky is invisible; albedo c shows
    c L where it covers the pixel; fuzz only loses energy (rays pushed into the surface)."""
    cls = sphere_pixel_classes(SPHERE_CAM, (0, 0, 0), 1.0)
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.metal(1.0, fuzz=0.0))
    np.testing.assert_allclose(scene.render(SPHERE_CAM, spp=4, sky=1.5), 1.5, rtol=1e-12)
    c = np.array([0.9, 0.6, 0.3])
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.metal(c, fuzz=0.0))
    img = scene.render(SPHERE_CAM, spp=4, sky=1.5)
    np.testing.assert_allclose(img[cls == 1], np.broadcast_to(1.5 * c, img[cls == 1].shape), rtol=1e-12)
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.metal(1.0, fuzz=0.8))
    img, var = scene.render(SPHERE_CAM, spp=16, sky=1.5, return_variance=True)
    inside = img[cls == 1]
    assert inside.max() <= 1.5 * (1 + 1e-12)
    lost = 1.5 - inside.mean()
    err = math.sqrt(var[cls == 1].sum()) / inside.size
    assert lost > SIGMAS * err, f"fuzzy metal: energy lost {lost} not above noise {err}"


@pytest.mark.parametrize("ior", [1.5, 2.4, 0.75])
def test_dielectric_conserves_energy(ior):
    """Clear glass reflects R and transmits 1 - R: a glass sphere in a uniform sky is invisible
    (every path leaves with the sky's radiance), also when ior < 1 (total internal reflection
    from outside). Paths longer than max_depth are cut; with 64 they are vanishingly rare."""
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.dielectric(ior))
    img = scene.render(SPHERE_CAM, spp=16, sky=1.0, max_depth=64)
    assert img.max() <= 1 + 1e-12
    short = np.count_nonzero(img < 1 - 1e-12)
    assert short <= 0.01 * img.size and img.mean() > 1 - 1e-3, (short, img.mean())


def test_dielectric_refracts_gradient_sky():
    """Under a gradient sky, glass does change the picture (it bends rays): the sphere's centre
    pixel sees the sky flipped (a ball lens inverts), darker than the sky behind it would be."""
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.dielectric(1.5))
    cam = R.Camera((0, 0, 4), (0, 0, 0), vfov=30, width=33, height=33)
    bottom, top = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    glass = scene.render(cam, spp=64, sky=(bottom, top), max_depth=32)
    # Rays through the upper part of the ball leave heading downwards and see the dark bottom.
    upper, lower = glass[8, 16, 0], glass[24, 16, 0]
    assert upper < 0.5 < lower, (upper, lower)


# ------------------------------------------------------------------ geometry


def test_sphere_silhouette():
    """A black sphere in a white sky: 0 on pixels the projected disk covers entirely, 1 on pixels
    it cannot reach, fractions only on the silhouette (whose pixel count ~ its perimeter)."""
    center, radius = np.array([0.3, -0.2, 0.1]), 0.8
    cam = R.Camera((0.5, 1.0, 4.0), (0, 0, 0), vfov=35, width=64, height=48)
    scene = R.Scene()
    scene.add_spheres([center], radius, R.lambertian(0.0))
    img = scene.render(cam, spp=16, sky=1.0)[..., 0]
    cls = sphere_pixel_classes(cam, center, radius)
    assert np.all(img[cls == 1] == 0), img[cls == 1].max()
    assert np.all(img[cls == -1] == 1), img[cls == -1].min()
    edge = cls == 0
    disk_px = (cls == 1).sum()
    assert edge.sum() < 4 * 2 * math.sqrt(math.pi * disk_px), (edge.sum(), disk_px)
    assert 0 < img[edge].mean() < 1
    hits = scene.primary_hits(cam)
    assert np.all(hits[cls == 1] == 0) and np.all(hits[cls == -1] == -1)


def random_scene(seed, spheres=300, triangles=300, planes=True):
    rng = np.random.default_rng(seed)
    scene = R.Scene()
    m = R.lambertian(0.5)
    scene.add_spheres(rng.uniform(-1, 1, (spheres, 3)), rng.uniform(0.01, 0.08, spheres), m)
    v = rng.uniform(-1, 1, (3 * triangles, 3))
    v[1::3] = v[0::3] + rng.normal(0, 0.15, (triangles, 3))
    v[2::3] = v[0::3] + rng.normal(0, 0.15, (triangles, 3))
    scene.add_mesh(v, np.arange(3 * triangles).reshape(-1, 3), m)
    if planes:
        scene.add_plane((0, -1.2, 0), (0, 1, 0), m)
        scene.add_plane((0, 0, -1.5), (0.1, 0.2, 1), m)
    return scene, rng


def test_bvh_matches_brute_force():
    """The BVH finds exactly the hit (t and primitive) that testing every primitive finds, for
    rays from outside and from inside the cloud, including misses."""
    scene, rng = random_scene(7)
    n = 20000
    origins = np.concatenate([rng.uniform(-3, 3, (n // 2, 3)), rng.uniform(-1, 1, (n // 2, 3))])
    dirs = rng.normal(size=(n, 3))
    t_bvh, id_bvh = scene.intersect(origins, dirs)
    t_ref, id_ref = scene.intersect(origins, dirs, brute_force=True)
    assert np.array_equal(id_bvh, id_ref), f"{np.count_nonzero(id_bvh != id_ref)} rays differ"
    assert np.array_equal(t_bvh, t_ref)
    kinds = np.bincount(np.searchsorted([300, 600, 602], id_ref[id_ref >= 0], side="right"), minlength=3)
    assert kinds.min() > 100, kinds  # spheres, triangles and planes were all hit
    assert np.count_nonzero(id_ref < 0) > 100


def test_bvh_many_particles_matches_brute_force():
    rng = np.random.default_rng(2)
    scene = R.Scene()
    scene.add_spheres(rng.normal(size=(20000, 3)), 0.01, R.lambertian(0.5))
    origins = rng.uniform(-4, 4, (2000, 3))
    dirs = -origins + rng.normal(0, 0.3, (2000, 3))
    t_bvh, id_bvh = scene.intersect(origins, dirs)
    t_ref, id_ref = scene.intersect(origins, dirs, brute_force=True)
    assert np.array_equal(id_bvh, id_ref) and np.array_equal(t_bvh, t_ref)
    assert np.count_nonzero(id_ref >= 0) > 200


def test_preview_matches_tracer_primary_hits():
    """The preview's visible primitive is the tracer's primary hit at every pixel centre."""
    scene, _ = random_scene(4, spheres=400, triangles=200)
    cam = R.Camera((0.3, 0.8, 3.5), (0, 0, 0), vfov=45, width=96, height=64)
    img, ids, depth = scene.preview(cam, return_ids=True)
    hits = scene.primary_hits(cam)
    assert np.array_equal(ids, hits), f"{np.count_nonzero(ids != hits)} pixels differ"
    assert img.shape == (64, 96, 3) and np.isfinite(img).all()
    assert np.isinf(depth[ids < 0]).all() and np.isfinite(depth[ids >= 0]).all()
    assert len(np.unique(ids)) > 100


def test_preview_sphere_silhouette_and_camera_inside():
    center, radius = np.array([0.3, -0.2, 0.1]), 0.8
    cam = R.Camera((0.5, 1.0, 4.0), (0, 0, 0), vfov=35, width=64, height=48)
    img, ids, _ = R.Scene().preview(cam, return_ids=True)
    assert (ids == -1).all()
    scene = R.Scene()
    scene.add_spheres([center], radius, R.lambertian(0.5))
    _, ids, _ = scene.preview(cam, return_ids=True)
    cls = sphere_pixel_classes(cam, center, radius)
    assert np.all(ids[cls == 1] == 0) and np.all(ids[cls == -1] == -1)
    # Camera inside a sphere and a triangle crossing the camera plane: whole-image boxes.
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 5.0, R.lambertian(0.5))
    scene.add_mesh([[-1, 0, 5], [1, 0, 5], [0, 0.2, -3]], [[0, 1, 2]], R.metal())
    inside = R.Camera((0, 0.5, 0), (0, 0.5, -1), width=40, height=30)
    _, ids, _ = scene.preview(inside, return_ids=True)
    assert np.array_equal(ids, scene.primary_hits(inside))
    assert (ids == 1).any() and (ids == 0).any()


def test_preview_function_and_shading():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (2000, 3))
    cam = R.Camera((0, 1, 4), (0, 0, 0), width=80, height=60)
    img = R.preview(cam, centers=x, radii=0.03, floor=-1.0, light=(0, 1, 0), ambient=0.0)
    assert img.shape == (60, 80, 3)
    # Floor pixels: normal (0, 1, 0) straight at the light, so exactly the floor's albedo 0.5.
    scene = R.Scene()
    scene.add_plane((0, -1, 0), (0, 1, 0), R.lambertian(0.5))
    _, ids, _ = scene.preview(cam, return_ids=True)
    floor_only = img[ids == 0]
    assert np.isclose(floor_only, 0.5).mean() > 0.3  # many floor pixels are not covered


def test_splat_spheres_sees_what_the_preview_sees():
    """The splat's visible sphere at every pixel is the preview's (itself the tracer's primary
    hit), its depth that distance in float32, and its normal the sphere's at the hit point."""
    rng = np.random.default_rng(11)
    centers = rng.uniform(-1, 1, (3000, 3))
    radii = rng.uniform(0.01, 0.08, 3000)
    cam = R.Camera((0.4, 0.9, 3.2), (0, 0, 0), vfov=50, width=120, height=90)
    scene = R.Scene()
    scene.add_spheres(centers, radii, R.lambertian(0.5))
    _, ids_ref, depth_ref = scene.preview(cam, return_ids=True)
    depth, normals, ids, hits = R.splat_spheres(cam, centers, radii)
    assert depth.dtype == np.float32 and normals.dtype == np.float32 and ids.dtype == np.int32
    assert np.array_equal(ids, ids_ref), f"{np.count_nonzero(ids != ids_ref)} pixels differ"
    hit = ids >= 0
    assert hits == hit.sum() > 0.3 * hit.size
    assert np.isinf(depth[~hit]).all() and (normals[~hit] == 0).all()
    # float32 holds the distance to half an ulp of ~4: 2.4e-7 relative.
    np.testing.assert_allclose(depth[hit], depth_ref[hit], rtol=2.4e-7)
    # The normal is (p - c) / r at the hit p on the ray through the pixel centre.
    frame_rows, frame_cols = np.nonzero(hit)
    p = np.asarray(cam.look_from) + depth_ref[hit][:, None] * camera_rays(cam, 0.5, 0.5)[frame_rows, frame_cols]
    expected = (p - centers[ids[hit]]) / radii[ids[hit]][:, None]
    np.testing.assert_allclose(normals[hit], expected, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(normals[hit], axis=1), 1, atol=2e-5)


def test_splat_spheres_one_radius_threads_and_bad_input():
    rng = np.random.default_rng(3)
    centers = rng.normal(size=(20000, 3))
    cam = R.Camera((0, 0.5, 6), (0, 0, 0), width=160, height=120)
    old = km.get_num_threads()
    try:
        km.set_num_threads(1)
        one = R.splat_spheres(cam, centers, 0.05)
        km.set_num_threads(2)
        two = R.splat_spheres(cam, centers, np.full(20000, 0.05))
    finally:
        km.set_num_threads(old)
    for a, b in zip(one[:3], two[:3]):
        assert np.array_equal(a, b)
    empty = R.splat_spheres(cam, np.zeros((0, 3)), 0.1)
    assert empty[3] == 0 and (empty[2] == -1).all()
    behind = R.splat_spheres(cam, [[0, 0, 20]], 0.5)  # behind the camera
    assert behind[3] == 0
    with pytest.raises(ValueError, match="radii"):
        R.splat_spheres(cam, centers, 0.0)
    with pytest.raises(ValueError, match="radii"):
        R.splat_spheres(cam, centers, np.ones(3))
    with pytest.raises(ValueError, match="centers"):
        R.splat_spheres(cam, np.ones((4, 2)), 0.1)
    with pytest.raises(ValueError, match="centers"):
        R.splat_spheres(cam, [[0, 0, np.nan]], 0.1)
    with pytest.raises(ValueError, match="camera"):
        R.splat_spheres("camera", centers, 0.1)


# ------------------------------------------------------------------ determinism and output


def test_deterministic_for_any_thread_count():
    scene, _ = random_scene(5, spheres=100, triangles=100)
    scene.add_spheres([[0, 0, 0]], 0.5, R.dielectric(1.5))
    scene.add_spheres([[0.6, 0.6, 0]], 0.3, R.metal(0.8, fuzz=0.2))
    cam = R.Camera((0, 0.5, 3), (0, 0, 0), width=24, height=18)
    old = km.get_num_threads()
    try:
        km.set_num_threads(1)
        one = scene.render(cam, spp=20, seed=9)  # two passes of samples
        km.set_num_threads(2)
        two = scene.render(cam, spp=20, seed=9)
        other = scene.render(cam, spp=20, seed=10)
    finally:
        km.set_num_threads(old)
    assert np.array_equal(one, two)
    assert not np.array_equal(one, other)


def test_render_returns_owned_array():
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.lambertian(0.5))
    img = scene.render(R.Camera((0, 0, 3), (0, 0, 0), width=8, height=6), spp=1)
    assert img.shape == (6, 8, 3) and img.dtype == np.float64 and img.flags.c_contiguous
    assert img.base is not None and img.flags.writeable and img.flags.owndata is False
    del scene
    assert np.isfinite(img).all()


def test_tone_map_and_png(tmp_path):
    image = np.zeros((4, 5, 3))
    image[0, 0] = [1, 0.25, 4.0]
    px = R.tone_map(image, exposure=1.0, gamma=2.0)
    assert px.dtype == np.uint8 and px[0, 0].tolist() == [255, 128, 255] and px[1, 1].tolist() == [0, 0, 0]
    path = R.to_png(image, tmp_path / "x.png", gamma=2.0)
    from matplotlib import image as mpl_image

    back = mpl_image.imread(path)
    assert back.shape[:2] == (4, 5)
    np.testing.assert_allclose(np.round(back[..., :3] * 255), px)
    assert not list(tmp_path.glob("*.tmp"))


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda s: s.add_spheres(np.zeros((2, 2)), 1.0, R.lambertian()), "centers"),
        (lambda s: s.add_spheres(np.zeros((2, 3)), -1.0, R.lambertian()), "radii"),
        (lambda s: s.add_spheres(np.zeros((2, 3)), [1.0, 2.0, 3.0], R.lambertian()), "radii"),
        (lambda s: s.add_spheres([[0, np.nan, 0]], 1.0, R.lambertian()), "centers"),
        (lambda s: s.add_spheres(np.zeros((1, 3)), 1.0, "red"), "material"),
        (lambda s: s.add_mesh(np.zeros((3, 3)), [[0, 1, 3]], R.lambertian()), "triangles"),
        (lambda s: s.add_mesh(np.zeros((3, 3)), [[0.0, 1.0, 2.0]], R.lambertian()), "triangles"),
        (lambda s: s.add_mesh(np.zeros((3, 2)), [[0, 1, 2]], R.lambertian()), "vertices"),
        (lambda s: s.add_plane((0, 0, 0), (0, 0, 0), R.lambertian()), "normal"),
        (lambda s: R.dielectric(0.0), "ior"),
        (lambda s: R.dielectric(np.nan), "ior"),
        (lambda s: R.lambertian(1.2), "albedo"),
        (lambda s: R.lambertian(0.5, emission=-1), "emission"),
        (lambda s: R.metal(0.5, fuzz=2), "fuzz"),
        (lambda s: R.emissive([1, 2]), "radiance"),
        (lambda s: R.Camera((0, 0, 1), (0, 0, 1)), "look_at"),
        (lambda s: R.Camera((0, 0, 1), (0, 0, 0), up=(0, 0, 2)), "up"),
        (lambda s: R.Camera((0, 0, 1), (0, 0, 0), width=0), "width"),
        (lambda s: R.Camera((0, 0, 1), (0, 0, 0), vfov=180), "vfov"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), spp=0), "spp"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), max_depth=0), "max_depth"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), seed=-1), "seed"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), sky=-1.0), "sky"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), sky=np.ones((3, 3))), "sky"),
        (lambda s: s.render(R.Camera((0, 0, 1), (0, 0, 0)), spp=1, return_variance=True), "spp"),
        (lambda s: s.render("camera"), "camera"),
        (lambda s: s.preview(R.Camera((0, 0, 1), (0, 0, 0)), ambient=2), "ambient"),
        (lambda s: s.intersect(np.zeros((2, 3)), np.zeros((2, 3))), "directions"),
        (lambda s: R.to_png(np.full((2, 2, 3), np.nan), "x.png"), "image"),
    ],
)
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call(R.Scene())


def test_empty_scene_shows_the_sky():
    img = R.Scene().render(R.Camera((0, 0, 1), (0, 0, 0), width=3, height=2), spp=2, sky=0.5)
    np.testing.assert_array_equal(img, 0.5)


def test_example_smoke(tmp_path):
    example = Path(__file__).resolve().parents[1] / "examples" / "render_spheres.py"
    subprocess.run([sys.executable, str(example), "--out", str(tmp_path / "cornell.png"),
                    "--width", "32", "--height", "24", "--spp", "2"], check=True, timeout=120)
    assert (tmp_path / "cornell.png").stat().st_size > 100


def test_render_stops_on_ctrl_c(ctrl_c_delay):
    """A render of minutes stops within a fraction of a second of SIGINT (KeyboardInterrupt)."""
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.lambertian(0.5))
    cam = R.Camera((0, 0, 3), (0, 0, 0), width=200, height=150)
    seconds = ctrl_c_delay(lambda: scene.render(cam, spp=100_000))
    assert seconds < 2.0, f"render took {seconds:.2f} s to honour Ctrl-C"


# ------------------------------------------------------------------ Blinn-Phong and shadows


def test_preview_blinn_phong_against_the_analytic_shading():
    # A plane y = 0 seen from (0.7, 2, 3): every floor pixel's shade is known in closed form,
    # albedo (ambient + (1 - ambient) n.l) + k_s (n.h)^s with h the half vector of l and the
    # direction from the hit point to the eye.
    albedo, ambient, ks, shininess = 0.4, 0.2, 0.5, 24.0
    light = np.array([0.3, 1.0, -0.2])
    scene = R.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(albedo))
    cam = R.Camera((0.7, 2.0, 3.0), (0, 0, 0), width=61, height=45)
    img, ids, depth = scene.preview(cam, light=light, ambient=ambient, specular=ks, shininess=shininess,
                                    return_ids=True)
    d = camera_rays(cam, 0.5, 0.5)
    hit = ids == 0
    p = np.asarray(cam.look_from) + depth[..., None] * d
    l = light / np.linalg.norm(light)
    v = np.asarray(cam.look_from) - p
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    h = l + v
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    n_dot_h = np.clip(h[..., 1], 0, None)
    expected = albedo * (ambient + (1 - ambient) * l[1]) + ks * n_dot_h**shininess
    assert hit.mean() > 0.5
    np.testing.assert_allclose(img[hit][:, 0], expected[hit], rtol=1e-9, atol=1e-12)
    # The highlight is where n.h is largest (the mirror point of the light), and it is specular:
    # Lambert alone (k_s = 0) is flat over the plane.
    peak = np.unravel_index(np.argmax(np.where(hit, img[..., 0], -1)), hit.shape)
    assert n_dot_h[peak] == pytest.approx(n_dot_h[hit].max(), rel=1e-6)
    flat = scene.preview(cam, light=light, ambient=ambient)
    np.testing.assert_allclose(flat[hit][:, 0], albedo * (ambient + (1 - ambient) * l[1]), rtol=1e-12)


def test_preview_soft_shadow_umbra_penumbra_and_light():
    # A ball of radius r at height H over the floor, the light straight up with angular radius
    # alpha. From a floor point the ball's centre is theta off the vertical and subtends beta =
    # asin(r / dist): the point is in the umbra if theta + alpha <= beta (V = 0), fully lit if
    # theta >= alpha + beta (V = 1), in between in the penumbra (0 <= V <= 1).
    r, H, alpha, albedo, ambient = 0.3, 1.0, 0.15, 0.5, 0.1
    scene = R.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), R.lambertian(albedo))
    scene.add_spheres([[0, H, 0]], r, R.lambertian(0.8))
    cam = R.Camera((0, 4.0, 2.0), (0, 0, 0), width=81, height=61)
    img, ids, depth = scene.preview(cam, light=(0, 1, 0), ambient=ambient, shadows=64, light_radius=alpha,
                                    return_ids=True)
    p = np.asarray(cam.look_from) + depth[..., None] * camera_rays(cam, 0.5, 0.5)
    floor = ids == 1
    to_ball = np.array([0, H, 0]) - p
    dist = np.linalg.norm(to_ball, axis=-1)
    theta = np.arccos(np.clip(to_ball[..., 1] / dist, -1, 1))
    beta = np.arcsin(np.clip(r / dist, 0, 1))
    umbra = floor & (theta + alpha <= beta - 1e-3)
    lit = floor & (theta >= alpha + beta + 1e-3)
    penumbra = floor & ~umbra & ~lit
    shade = img[..., 0] / albedo
    assert umbra.sum() > 20 and lit.sum() > 100 and penumbra.sum() > 20
    np.testing.assert_allclose(shade[umbra], ambient, rtol=1e-12)
    np.testing.assert_allclose(shade[lit], 1.0, rtol=1e-12)
    assert np.all((shade[penumbra] >= ambient - 1e-12) & (shade[penumbra] <= 1 + 1e-12))
    # The penumbra is a gradient, not a hard edge: many distinct visible fractions.
    assert len(np.unique(np.round(shade[penumbra], 6))) > 10
    # Shadows off: the floor under the ball is lit.
    plain = scene.preview(cam, light=(0, 1, 0), ambient=ambient)
    np.testing.assert_allclose(plain[umbra][:, 0] / albedo, 1.0, rtol=1e-12)


@pytest.mark.parametrize("kwargs, name", [({"specular": -1}, "specular"), ({"shininess": 0}, "shininess"),
                                          ({"shadows": -2}, "shadows"), ({"shadows": 1.5}, "shadows"),
                                          ({"light_radius": 2.0}, "light_radius")])
def test_preview_shading_arguments_checked(kwargs, name):
    scene = R.Scene()
    scene.add_spheres([[0, 0, 0]], 1.0, R.lambertian(0.5))
    with pytest.raises(ValueError, match=name):
        scene.preview(R.Camera((0, 0, 3), (0, 0, 0), width=8, height=6), **kwargs)


# ------------------------------------------------------------------ notebooks


def test_show_image_and_run_inline(tmp_path):
    img = np.zeros((6, 8, 3), np.uint8)
    img[:, :4] = (255, 0, 0)
    shown = km.show(img)
    png = shown._repr_png_()
    assert png.startswith(b"\x89PNG")
    from matplotlib import image as mpl_image

    path = shown.save(tmp_path / "x.png")
    np.testing.assert_array_equal((mpl_image.imread(path)[..., :3] * 255).round().astype(np.uint8), img)
    run = km.show("vortex_merge", quick=True, frames=3, out=tmp_path / "run",
                  overrides=[("output.mp4", False)])
    assert isinstance(run, km.notebook.Image) and run.pixels.ndim == 3
    with pytest.raises(ValueError, match="source"):
        km.show(42)


def test_smoke_ray_march_shows_the_density_where_it_projects():
    # A ball of smoke in a 24^3 box: its pixels differ from the empty box's frame, pixels whose
    # rays miss the ball's bounding sphere are exactly the empty frame, and the ball's lit top
    # is brighter than its self-shadowed bottom (the light comes from above).
    from kinema.scenes import render3d

    n, h = 24, 1.0 / 24
    c = (np.arange(n) + 0.5) * h
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    centre, radius = np.array([0.5, 0.5, 0.5]), 0.2
    rho = ((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2 < radius**2).astype(float)
    output = {"camera": None, "width": 96, "height": None, "view": None}
    img = render3d.smoke_image(rho, h, output).astype(int)
    empty = render3d.smoke_image(np.zeros_like(rho), h, output).astype(int)
    cam = render3d.camera(output, render3d.Geometry(np.zeros(3), np.ones(3)), (0, 1), None)
    d = render3d.camera_rays(cam)
    to_c = centre - np.asarray(cam.look_from)
    along = d @ to_c
    miss = np.linalg.norm(to_c) ** 2 - along**2 > (radius + 1.5 * h) ** 2  # ray passes outside the ball
    changed = np.abs(img - empty).sum(axis=2) > 0
    assert not changed[miss].any()
    assert changed[~miss].mean() > 0.8
    rows = np.flatnonzero((~miss).any(axis=1))
    col = img.shape[1] // 2
    top, bottom = img[rows[2], col].sum(), img[rows[-3], col].sum()
    assert top > bottom, (top, bottom)
