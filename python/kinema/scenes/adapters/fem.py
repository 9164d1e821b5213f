"""Scenes on km.fem.Body: one soft body of linear tetrahedra (3D).

Objects (exactly one): ``box`` (km.fem.box_mesh) or ``mesh`` (the tetrahedra of a mesh file),
each with its material and fixed regions. Steps: ``substeps`` equal implicit (projected Newton)
or symplectic steps per frame. The linear solver is "cholmod" or "cg" (state-only: resumed
runs repeat straight runs bit for bit; "cholmod_pcg" keeps a factor across steps).
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes.adapters.deformable import FIXED, MESH_FIELDS, DeformableSimulation, fixed_vertices, read_mesh
from kinema.scenes.preview import boundary_faces
from kinema.scenes.schema import Field, Int, Real, Str, Table, Vec

SOLVER = Table({
    "integrator": Field(Str(("implicit", "symplectic")), "implicit"),
    "substeps": Field(Int(ge=1), 1, "steps per frame"),
    "tol": Field(Real(gt=0), 1e-6, "Newton tolerance (relative gradient norm)"),
    "max_newton": Field(Int(ge=1), 50),
    # Scenes resume from checkpoints bit for bit, so their default solver keeps no history:
    # "cholmod" (the library default) reuses the CHOLMOD factor of earlier steps as a PCG
    # preconditioner, which a resumed run does not have (same answer to the solver tolerance,
    # not to the last bit).
    "linear_solver": Field(Str(("cholmod_direct", "cholmod", "cg")), "cholmod_direct"),
    "gravity": Field(Vec(spatial=True), None, "[m/s^2]"),
})

_MATERIAL = {
    "model": Field(Str(km.fem.MODELS), "neohookean"),
    "youngs_modulus": Field(Real(gt=0), doc="[Pa]"),
    "poisson_ratio": Field(Real(gt=-1, le=0.499)),
    "density": Field(Real(gt=0), doc="[kg/m^3]"),
    "damping": Field(Real(ge=0), 0.0, "mass-proportional damping [1/s]"),
    "fixed": FIXED,
}
OBJECTS = {
    "box": Table({"lower": Field(Vec(spatial=True)), "upper": Field(Vec(spatial=True)),
                  "cells": Field(Vec(3, Int(ge=1)), doc="cells per axis (6 tetrahedra each)"),
                  **_MATERIAL}, "a box of tetrahedra"),
    "mesh": Table({**MESH_FIELDS, **_MATERIAL}, "the tetrahedra of a mesh file"),
}


def dimension(solver, objects):
    return 3


class FEMSimulation(DeformableSimulation):
    NAME = "body"
    DIAGNOSTICS = ("energy", "newton_iterations")

    def __init__(self, scene):
        super().__init__(scene)
        objects = scene.config["objects"]
        if len(objects) != 1:
            raise scene.error("objects", f"a fem scene holds exactly one body (box or mesh), got {len(objects)}")
        obj = objects[0]
        if obj["type"] == "box":
            V, T = km.fem.box_mesh(obj["lower"], obj["upper"], tuple(obj["cells"]))
        else:
            V, T = read_mesh(scene, 0, obj, ("tetra",))
        fixed = fixed_vertices(V, obj["fixed"])
        try:
            self.body = km.fem.Body(V, T, model=obj["model"], youngs_modulus=obj["youngs_modulus"],
                                    poisson_ratio=obj["poisson_ratio"], density=obj["density"], fixed=fixed,
                                    gravity=self.options["gravity"], damping=obj["damping"])
        except ValueError as exc:
            raise scene.error("objects[0]", str(exc)) from None
        self.surface = boundary_faces(T)
        self.cells = [("tetra", T)]
        self.rest = np.array(V, float)
        self.rest_box = (V.min(axis=0), V.max(axis=0))
        self.newton = 0

    def _step(self, dt):
        o = self.options
        if o["integrator"] == "symplectic":
            self.body.step(dt, "symplectic")
        else:
            info = self.body.step(dt, "implicit", tol=o["tol"], max_newton=o["max_newton"],
                                  linear_solver=o["linear_solver"])
            self.newton = info.iterations

    def diagnostics(self):
        return {"energy": self.body.energy(), "newton_iterations": float(self.newton)}

    # The body's own state() (its lagged factor included, so that a resumed scene is bitwise
    # the uninterrupted one), with the scene's frame counter beside it.
    def get_state(self):
        state = self.body.state()
        state["solver_steps"] = state.pop("steps")
        state["steps"] = np.int64(self.steps)
        return state

    def set_state(self, state):
        state = dict(state)
        self.steps = int(state.pop("steps"))
        state["steps"] = state.pop("solver_steps")
        self.body.set_state(state)


Simulation = FEMSimulation
