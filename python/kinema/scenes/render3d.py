"""Frames of 3D particle and mesh scenes through km.render: ``output.render = "preview"`` (the
z-buffered preview under a perspective camera) or ``"pathtrace"`` (the path tracer).

An adapter that supports it gives its frame as a :class:`Geometry` (spheres and meshes with
their materials, and a fixed box the camera frames). Each frame builds a km.render.Scene of
that geometry on a grey ground plane under the default sky. The image depends on the
simulation state and the ``[output]`` table only (the path tracer's seed is ``output.seed``),
so a resumed run draws the same frames bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import kinema as km

MODES = ("flat", "preview", "pathtrace")
GROUND = km.render.lambertian(0.5)


@dataclass
class Geometry:
    """What a frame shows: spheres [(centres (n, 3), radius, material)], meshes [(vertices,
    triangles, material)] and the box (lower, upper) the camera frames, fixed over the run;
    the ground plane lies under it, normal to the view's up axis."""

    lower: np.ndarray
    upper: np.ndarray
    spheres: list = field(default_factory=list)
    meshes: list = field(default_factory=list)


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
        direction = toward + 0.3 * up + 0.3 * right
        reach = 0.5 * np.linalg.norm(hi - lo) / math.sin(math.radians(vfov) / 2)
        look_from = np.asarray(look_at) + 0.85 * reach * direction / np.linalg.norm(direction)
    width = output["width"]
    height = output["height"] or max(16, round(0.75 * width))
    try:
        return km.render.Camera(look_from, look_at, c.get("up") or up, vfov, width=width, height=height)
    except ValueError as exc:
        raise error("output.camera", str(exc)) from None


def image(geometry, output, axes, error):
    """The frame as an (H, W, 3) uint8 image (output.render "preview" or "pathtrace").
    error(path, message): the scene's error constructor, for a camera that cannot be built."""
    cam = camera(output, geometry, axes, error)
    right, up, toward = _basis(axes)
    scene = km.render.Scene()
    for centers, radius, material in geometry.spheres:
        if len(centers):
            scene.add_spheres(centers, radius, material)
    for vertices, triangles, material in geometry.meshes:
        if len(triangles):
            scene.add_mesh(vertices, triangles, material)
    scene.add_plane(np.where(up > 0, geometry.lower, 0.0), up, GROUND)
    if output["render"] == "pathtrace":
        linear = scene.render(cam, spp=output["spp"], max_depth=output["max_depth"], seed=output["seed"])
    else:
        linear = scene.preview(cam, light=up + 0.3 * right + 0.5 * toward)
    return km.render.tone_map(linear)
