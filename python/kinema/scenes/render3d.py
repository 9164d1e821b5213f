"""Frames of 3D particle and mesh scenes through km.render: ``output.render = "preview"`` (the
z-buffered preview under a perspective camera, Blinn-Phong shading with soft shadows) or
``"pathtrace"`` (the path tracer).

An adapter that supports it gives its frame as a :class:`Geometry`: spheres and meshes with
their materials, liquids (particles whose free surface km.surface reconstructs and which are
drawn as water), solid boxes, the tank's frame, and the box the camera frames. Each frame is
set on a two-tone checker floor under the default sky, lit by a distant light from above, the
right and the front. The image depends on the simulation state and the ``[output]`` table only
(the path tracer's seed is ``output.seed``), so a resumed run draws the same frames bit for bit.

One up axis for every scene: y (gravity (0, -9.81, 0) in the shipped scenes), the view axes
(0, 1) by default, x to the right; ``output.view`` changes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import kinema as km

MODES = ("flat", "preview", "pathtrace")
GROUND = km.render.lambertian(0.5)
FLOOR_LIGHT = km.render.lambertian(0.62)
FLOOR_DARK = km.render.lambertian(0.42)
FRAME = km.render.lambertian(0.25)
#: Water's absorption per length of the scene's box diagonal: a red-absorbing blue-green.
WATER_ABSORPTION = np.array([7.0, 2.5, 1.0])
#: The dark sky of smoke frames: white smoke stands out.
NIGHT_SKY = ((0.002, 0.002, 0.003), (0.01, 0.013, 0.02))
#: Preview shading of the scenes' frames (km.render.Scene.preview's arguments).
SHADING = {"ambient": 0.3, "specular": 0.25, "shininess": 48.0, "shadows": 12, "light_radius": 0.12}


@dataclass
class Geometry:
    """What a frame shows: spheres [(centres (n, 3), radius, material)], meshes [(vertices,
    triangles, material)], liquids [(particle positions (n, 3), spacing)] drawn as their
    reconstructed free surface, boxes [(lower, upper, material)] (obstacles), and the box
    (lower, upper) the camera frames, fixed over the run; ``tank`` draws that box's edges.
    The floor lies under the box, normal to the view's up axis."""

    lower: np.ndarray
    upper: np.ndarray
    spheres: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    liquids: list = field(default_factory=list)
    boxes: list = field(default_factory=list)
    tank: bool = False


def _basis(axes):
    """Unit vectors (right, up, towards the viewer) of the view axes (a, b)."""
    right, up = np.eye(3)[axes[0]], np.eye(3)[axes[1]]
    return right, up, np.cross(right, up)


def camera(output, geometry, axes, error):
    """The km.render.Camera of ``output.camera``; missing keys are computed from the box: it
    looks at the box centre from the viewer's side of the view axes, a little from above and
    the right, far enough that the box's bounding sphere fills the vertical field of view."""
    c = output["camera"] or {}
    lo, hi = np.asarray(geometry.lower, float), np.asarray(geometry.upper, float)
    right, up, toward = _basis(axes)
    vfov = c.get("vfov") or 40.0
    look_at = c.get("look_at") or (lo + hi) / 2
    look_from = c.get("look_from")
    if look_from is None:
        direction = toward + 0.45 * up + 0.35 * right
        reach = 0.5 * np.linalg.norm(hi - lo) / math.sin(math.radians(vfov) / 2)
        look_from = np.asarray(look_at) + 0.85 * reach * direction / np.linalg.norm(direction)
    width = output["width"]
    height = output["height"] or max(16, round(0.75 * width))
    try:
        return km.render.Camera(look_from, look_at, c.get("up") or up, vfov, width=width, height=height)
    except ValueError as exc:
        raise error("output.camera", str(exc)) from None


# ------------------------------------------------------------------ meshes of the set


def box_mesh(lower, upper):
    """The 12 outward triangles of the axis-aligned box [lower, upper]: (8, 3) vertices, (12, 3)."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    v = lo + corners * (hi - lo)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    t = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], np.int64)
    return v, t


def frame_mesh(lower, upper, width):
    """The 12 edges of the box [lower, upper] as square beams of side ``width``."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    verts, tris = [], []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for s0 in (0, 1):
            for s1 in (0, 1):
                c = lo.copy()
                c[others[0]] = (lo, hi)[s0][others[0]]
                c[others[1]] = (lo, hi)[s1][others[1]]
                b_lo, b_hi = c - width / 2, c + width / 2
                b_lo[axis], b_hi[axis] = lo[axis] - width / 2, hi[axis] + width / 2
                v, t = box_mesh(b_lo, b_hi)
                tris.append(t + sum(len(x) for x in verts))
                verts.append(v)
    return np.concatenate(verts), np.concatenate(tris)


def checker_floor(geometry, up, height, tiles=14):
    """Two meshes (light, dark tiles) of a square checker floor normal to ``up`` at ``height``,
    centred under the box and three times its footprint, with square tiles."""
    lo, hi = np.asarray(geometry.lower, float), np.asarray(geometry.upper, float)
    u, w = [a for a in range(3) if a != up]
    centre = (lo + hi) / 2
    side = 3.0 * max(hi[u] - lo[u], hi[w] - lo[w])
    tile = side / tiles
    g = (np.arange(tiles + 1) - tiles / 2) * tile
    verts = np.zeros(((tiles + 1) ** 2, 3))
    verts[:, u] = np.repeat(g + centre[u], tiles + 1)
    verts[:, w] = np.tile(g + centre[w], tiles + 1)
    verts[:, up] = height
    i, j = np.meshgrid(np.arange(tiles), np.arange(tiles), indexing="ij")
    q = (i * (tiles + 1) + j).ravel()
    quads = np.stack([q, q + tiles + 1, q + tiles + 2, q + 1], 1)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    odd = np.tile(((i + j) % 2).ravel().astype(bool), 2)
    return (verts, tris[~odd]), (verts, tris[odd])


def checker_split(rest, triangles):
    """A checker pattern fixed to a deforming mesh: True for the triangles whose rest-state
    centroid lies in an odd cell of a grid of twice the short edges' length (on structured
    meshes each check is 2 x 2 elements; the pattern moves and stretches with the material)."""
    rest = np.asarray(rest, float)
    t = np.asarray(triangles)
    c = rest[t].mean(axis=1)
    edges = np.concatenate([rest[t[:, a]] - rest[t[:, b]] for a, b in ((0, 1), (1, 2), (2, 0))])
    size = 2 * np.percentile(np.linalg.norm(edges, axis=1), 25)  # the short (not diagonal) edges
    k = np.floor((c - rest.min(0)) / size + 1e-9).astype(np.int64)
    return k.sum(axis=1) % 2 == 1


def liquid_surface(points, spacing):
    """The free surface of the particles (km.surface's marching cubes: bitwise reproducible, as
    a resumed run's frames must be; splashsurf's threaded sums are not), or None when
    scikit-image is not installed (the particles are then drawn as spheres)."""
    for method in ("marching_cubes",):
        try:
            return km.surface.reconstruct(points, spacing, method=method)
        except ImportError:
            continue
    return None


def build(geometry, axes, horizon=True):
    """The km.render.Scene of a frame (horizon: a grey ground plane beyond the checker floor)."""
    right, up, toward = _basis(axes)
    up_axis = int(np.argmax(np.abs(up)))
    lo, hi = np.asarray(geometry.lower, float), np.asarray(geometry.upper, float)
    scene = km.render.Scene()
    for centers, radius, material in geometry.spheres:
        if len(centers):
            scene.add_spheres(centers, radius, material)
    for vertices, triangles, material in geometry.meshes:
        if len(triangles):
            scene.add_mesh(vertices, triangles, material)
    for points, spacing in geometry.liquids:
        if not len(points):
            continue
        mesh = liquid_surface(points, spacing)
        if mesh is None or not len(mesh.triangles):
            scene.add_spheres(points, 0.5 * spacing, km.render.lambertian((0.15, 0.4, 0.8)))
        else:
            water = km.render.dielectric(1.33, absorption=WATER_ABSORPTION / float(np.linalg.norm(hi - lo)))
            scene.add_mesh(mesh.vertices, mesh.triangles, water)
    for b_lo, b_hi, material in geometry.boxes:
        scene.add_mesh(*box_mesh(b_lo, b_hi), material)
    extent = float(np.linalg.norm(hi - lo))
    if geometry.tank:
        scene.add_mesh(*frame_mesh(lo, hi, 0.006 * extent), FRAME)
    # The floor just under the box (a hair below, so that what rests on the box's floor
    # does not fight it for depth), then an infinite plane a little lower for the horizon.
    height = lo[up_axis] - 1e-4 * extent if up[up_axis] > 0 else hi[up_axis] + 1e-4 * extent
    light, dark = checker_floor(geometry, up_axis, height)
    scene.add_mesh(*light, FLOOR_LIGHT)
    scene.add_mesh(*dark, FLOOR_DARK)
    if horizon:
        base = np.zeros(3)
        base[up_axis] = height - 1e-3 * extent * np.sign(up[up_axis])
        scene.add_plane(base, up, GROUND)
    return scene


def image(geometry, output, axes, error):
    """The frame as an (H, W, 3) uint8 image (output.render "preview" or "pathtrace").
    error(path, message): the scene's error constructor, for a camera that cannot be built."""
    cam = camera(output, geometry, axes, error)
    right, up, toward = _basis(axes)
    scene = build(geometry, axes)
    if output["render"] == "pathtrace":
        linear = scene.render(cam, spp=output["spp"], max_depth=output["max_depth"], seed=output["seed"])
    else:
        linear = scene.preview(cam, light=up + 0.4 * right + 0.6 * toward, **SHADING)
    return km.render.tone_map(linear)


# ------------------------------------------------------------------ volumes (smoke)


def camera_rays(cam):
    """Unit directions (H, W, 3) of the pinhole camera's rays through the pixel centres (the
    model of km.render.Camera: row 0 at the top)."""
    eye, at, up = (np.asarray(v, float) for v in (cam.look_from, cam.look_at, cam.up))
    w = (eye - at) / np.linalg.norm(eye - at)
    u = np.cross(up, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    half = math.tan(math.radians(cam.vfov) / 2)
    x = ((np.arange(cam.width) + 0.5) / cam.width * 2 - 1) * half * cam.width / cam.height
    y = (1 - (np.arange(cam.height) + 0.5) / cam.height * 2) * half
    d = -w + x[None, :, None] * u + y[:, None, None] * v
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def smoke_image(density, h, output, obstacles=(), error=None, *, extinction=None, albedo=(0.92, 0.93, 0.96)):
    """A 3D density field ray-marched into an (H, W, 3) uint8 frame, over the preview of its
    box's floor and its obstacles (scene regions: spheres and boxes) under a dark sky (y up,
    the camera of :func:`camera` on the grid's box).

    Emission-absorption with single scattering from a light above (Max 1995, "Optical models for
    direct volume rendering"): along each ray, front to back, a step ds at density rho adds
    T (1 - exp(-sigma rho ds)) albedo (ambient + L), T is the transmittance so far, and L the
    light reaching the sample, exp(-sigma * (density integrated up to the top of the box)).
    sigma (extinction, [1/(density m)]) defaults to 30 / (box height * max density): a plume a
    tenth of the box thick at half the peak density has optical depth 1.5 (its shape reads, its
    lit side bright and its lower side in its own shadow).
    """
    from scipy.ndimage import map_coordinates

    rho = np.clip(np.asarray(density, float), 0, None)
    shape = np.array(rho.shape)
    lo, hi = np.zeros(3), shape * h
    geo = Geometry(lo, hi, tank=True)
    for region in obstacles:
        if region["shape"] == "sphere":
            geo.spheres.append((np.atleast_2d(region["center"]), region["radius"], km.render.lambertian(0.6)))
        else:
            geo.boxes.append((region["lower"], region["upper"], km.render.lambertian(0.6)))
    axes = tuple(output["view"] or (0, 1))
    err = error or (lambda path, message: ValueError(f"{path}: {message}"))
    cam = camera(output, geo, axes, err)
    right, up, toward = _basis(axes)
    scene = build(geo, axes, horizon=False)
    background, _, depth = scene.preview(cam, light=up + 0.4 * right + 0.6 * toward, return_ids=True,
                                         sky=NIGHT_SKY, **SHADING)
    peak = float(rho.max())
    if peak <= 0:
        return km.render.tone_map(background)
    sigma = extinction or 30.0 / (hi[1] * peak)
    # Light reaching each cell from above: the density integrated over the cells above it.
    above = np.cumsum(rho[:, ::-1, :], axis=1)[:, ::-1, :] - 0.5 * rho
    light = np.exp(-sigma * above * h)
    d = camera_rays(cam)
    eye = np.asarray(cam.look_from, float)
    # The part of each ray inside the box (slab test), never beyond the opaque background hit.
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.where(d != 0, (lo - eye) / d, -np.inf)
        t1 = np.where(d != 0, (hi - eye) / d, np.inf)
    t_in = np.maximum(np.minimum(t0, t1).max(-1), 0)
    t_out = np.minimum(np.maximum(t0, t1).min(-1), depth)
    hit = t_out > t_in
    ds = 0.5 * h
    n = int(np.ceil((t_out[hit] - t_in[hit]).max(initial=0) / ds))
    dirs, start, stop = d[hit], t_in[hit], t_out[hit]
    trans = np.ones(len(dirs))
    colour = np.zeros(len(dirs))
    for k in range(n):
        t = start + (k + 0.5) * ds
        live = (t < stop) & (trans > 1e-3)
        if not live.any():
            break
        p = (eye + t[live, None] * dirs[live]) / h - 0.5  # cell-centre coordinates
        r = map_coordinates(rho, p.T, order=1, mode="constant", cval=0.0)
        lit = map_coordinates(light, p.T, order=1, mode="nearest")
        alpha = 1 - np.exp(-sigma * r * ds)
        colour[live] += trans[live] * alpha * (0.35 + 0.65 * lit)
        trans[live] *= 1 - alpha
    out = background.copy()
    px = out[hit]
    out[hit] = px * trans[:, None] + colour[:, None] * np.asarray(albedo)
    return km.render.tone_map(out)
