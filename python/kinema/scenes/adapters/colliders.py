"""``collider`` objects (also spelled ``obstacle``) of the mass-spring and fem scenes: planes,
boxes (optionally rotated), spheres and triangle-mesh files, static or moving at a constant
velocity, handed to km.contact (implicit steps: IPC; symplectic steps: projection, planes,
axis-aligned boxes and spheres only), and drawn grey in the frames."""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes.adapters.deformable import read_mesh
from kinema.scenes.schema import Field, Real, Str, Table, Vec

COLLIDER = Table({
    "shape": Field(Str(("plane", "box", "sphere", "mesh"))),
    "point": Field(Vec(spatial=True), None, "plane: a point on it [m]"),
    "normal": Field(Vec(spatial=True), None, "plane: the normal towards the free side"),
    "lower": Field(Vec(spatial=True), None, "box: lower corner [m]"),
    "upper": Field(Vec(spatial=True), None, "box: upper corner [m]"),
    "rotation": Field(Vec(3, Real()), None, "box: rotation about its centre, degrees about x, y then z"),
    "center": Field(Vec(spatial=True), None, "sphere: centre [m]"),
    "radius": Field(Real(gt=0), None, "sphere: radius [m]"),
    "file": Field(Str(), None, "mesh: a triangle-mesh file meshio reads (relative to the scene file)"),
    "scale": Field(Real(gt=0), 1.0, "mesh: scale factor"),
    "offset": Field(Vec(spatial=True), None, "mesh: translation after scaling [m]"),
    "velocity": Field(Vec(spatial=True), None, "constant velocity of a moving collider [m/s]"),
    "friction": Field(Real(ge=0), None, "symplectic steps: this collider's Coulomb mu (default: the solver's)"),
}, "a static or moving collider the bodies cannot pass (km.contact)")

GREY = km.render.lambertian((0.55, 0.57, 0.6))


def _rotation(deg):
    ax, ay, az = np.radians(deg)
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def collider_args(scene, k, obj):
    """(shape, keyword options) of km.contact's ``add_collider`` for objects[k]."""
    need = {"plane": ("point", "normal"), "box": ("lower", "upper"), "sphere": ("center", "radius"),
            "mesh": ("file",)}[obj["shape"]]
    for key in need:
        if obj[key] is None:
            raise scene.error(f"objects[{k}].{key}", f"a {obj['shape']} collider needs {key}")
    kw = {}
    if obj["velocity"] is not None:
        kw["velocity"] = obj["velocity"]
    if obj["friction"] is not None:
        kw["friction"] = obj["friction"]
    shape = obj["shape"]
    if shape == "plane":
        kw.update(point=obj["point"], normal=obj["normal"])
    elif shape == "sphere":
        kw.update(center=obj["center"], radius=obj["radius"])
    elif shape == "box" and obj["rotation"] is None:
        kw.update(lower=obj["lower"], upper=obj["upper"])
    elif shape == "box":
        v, t = km.contact.box_surface(obj["lower"], obj["upper"])
        c = v.mean(axis=0)
        shape, kw["vertices"], kw["triangles"] = "mesh", (v - c) @ _rotation(obj["rotation"]).T + c, t
    else:
        kw["vertices"], kw["triangles"] = read_mesh(scene, k, obj, ("triangle",))
    return shape, kw


def split(objects):
    """(body objects, [(index, collider object)])."""
    bodies = [o for o in objects if o["type"] not in ("collider", "obstacle")]
    colliders = [(k, o) for k, o in enumerate(objects) if o["type"] in ("collider", "obstacle")]
    return bodies, colliders


def meshes(contact_scene):
    """Render meshes [(vertices, triangles, material)] of a km.contact.Scene's colliders at
    their current positions (planes are the frame's floor)."""
    out = []
    faces = contact_scene.faces
    for spec in contact_scene.colliders:
        rows = spec["rows"]
        if rows is None or spec["shape"] == "plane":  # a moving plane's one row is its point
            continue
        sel = (faces >= rows.start).all(axis=1) & (faces < rows.stop).all(axis=1)
        out.append((contact_scene.x, faces[sel], GREY))
    return out


def frame_box(lo, hi, contact_scene, up):
    """The frame's box (lo, hi) grown to hold the colliders (their vertices as built), with its
    floor on the lowest plane collider normal to the up axis when there is one."""
    lo, hi = lo.copy(), hi.copy()
    floors = []
    for spec in contact_scene.colliders:
        if spec["shape"] == "plane":
            if abs(abs(spec["normal"][up]) - 1) < 1e-12:
                floors.append(spec["point"][up])
            continue
        v = spec["rest"]
        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
    if floors:
        lo[up] = min(floors)
    return lo, hi
