"""What the mass-spring and FEM adapters share: meshes from files, fixed regions, fixed-size
substeps, the (x, v, time, step count) state, mesh output and the shaded preview."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import kinema as km
from kinema.scenes import preview, regions, render3d
from kinema.scenes.adapters.base import ArrayStateSimulation, PointData, view_camera
from kinema.scenes.schema import REGION, Field, ListOf, Real, Str, Vec

MESH_FIELDS = {
    "file": Field(Str(), doc="a mesh file meshio reads (relative to the scene file)"),
    "scale": Field(Real(gt=0), 1.0),
    "offset": Field(Vec(spatial=True), None, "translation after scaling [m]"),
}
FIXED = Field(ListOf(REGION), [], "vertices inside any of these regions are held in place")


def read_mesh(scene, k, obj, kinds):
    """(vertices, cells) of the first cell block of one of ``kinds`` in the object's mesh file."""
    import meshio

    path = Path(obj["file"])
    if not path.is_absolute():
        path = Path(scene.path).parent / path
    try:
        mesh = meshio.read(path)
    except Exception as exc:  # meshio raises several types for unreadable files
        raise scene.error(f"objects[{k}].file", f"cannot read {path}: {exc}") from None
    for block in mesh.cells:
        if block.type in kinds:
            x = mesh.points[:, :scene.dim] * obj["scale"]
            if obj["offset"] is not None:
                x = x + obj["offset"]
            return np.ascontiguousarray(x), np.asarray(block.data, np.int64)
    raise scene.error(f"objects[{k}].file", f"{path} has no cells of type {' or '.join(kinds)}")


def fixed_vertices(x, fixed):
    keep = np.zeros(len(x), bool)
    for region in fixed:
        keep |= regions.contains(region, x)
    return np.flatnonzero(keep)


class DeformableSimulation(ArrayStateSimulation):
    """Subclasses set self.body (x, v views and a _core with time/step_count),
    self.surface (triangles for preview and PLY), self.cells (meshio cells), self.rest (the
    initial vertices), self.rest_box (their bounding box) and ``_step(dt)``."""

    STEP_ATTR = "step_count"

    def __init__(self, scene):
        super().__init__(scene)
        self.dim = 3
        self.options = scene.config["solver"]
        self.substeps = self.options["substeps"]

    @property
    def time(self):
        return self.body.time

    def _step(self, dt):
        raise NotImplementedError

    def advance_to(self, t_end):
        # Fixed substeps: the step size depends on the frame length only, never on the state.
        dt = (t_end - self.body.time) / self.substeps
        for _ in range(self.substeps):
            self._step(dt)
        self.steps += self.substeps
        return self.substeps

    def _arrays(self):
        return {"x": self.body.x, "v": self.body.v}

    def _core(self):
        return self.body._core

    MATERIAL = km.render.lambertian((0.85, 0.4, 0.25))
    CHECKER = km.render.lambertian((0.95, 0.85, 0.7))

    def geometry(self, axes):
        """The surface triangles in a box fixed by the initial shape, with room below for the
        body to hang by its own size (the ground lies under that room)."""
        lo, hi = (b.copy() for b in self.rest_box)
        reach = (hi - lo).max()
        lo, hi = lo - 0.15 * reach, hi + 0.15 * reach
        lo[axes[1]] = self.rest_box[0][axes[1]] - 1.1 * reach
        lo, hi = self._frame_box(lo, hi, axes[1])
        # A checker fixed to the material, so that stretching and folds show.
        odd = render3d.checker_split(self.rest, self.surface)
        return render3d.Geometry(lo, hi, meshes=[(self.body.x, self.surface[~odd], self.MATERIAL),
                                                 (self.body.x, self.surface[odd], self.CHECKER)])

    def _frame_box(self, lo, hi, up):
        """Subclasses with colliders grow the frame to hold them."""
        return lo, hi

    def image(self, output):
        if output["render"] != "flat":
            axes = output["view"] or (0, 1)
            return render3d.image(self.geometry(axes), output, axes, self.scene.error)
        # The view is fixed by the initial shape (built before a checkpoint is restored), with
        # room below for the body to hang and swing by its own size.
        lo, hi = self.rest_box
        reach = (hi - lo).max()
        lo, hi = lo - 0.6 * reach, hi + 0.6 * reach
        up = (output["view"] or (0, 1))[1]
        lo[up], hi[up] = self.rest_box[0][up] - 1.1 * reach, self.rest_box[1][up] + 0.3 * reach
        cam = view_camera(output, 3, lo, hi, (0, 1))
        return preview.triangles(cam, self.body.x, self.surface)

    def data(self):
        b = self.body
        return [PointData(self.NAME, b.x.copy(), self.cells, {"velocity": b.v.copy()}, self.surface)]
