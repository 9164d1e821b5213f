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


def build(geometry, axes):
    """The km.render.Scene of a frame."""
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
