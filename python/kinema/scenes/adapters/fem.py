"""Scenes on km.fem.Body: soft bodies of linear tetrahedra (3D).

Objects: ``box`` (km.fem.box_mesh) or ``mesh`` (the tetrahedra of a mesh file), each with its
material and fixed regions, and ``collider`` (or ``obstacle``): planes, boxes, spheres, meshes.
One body without colliders steps alone; several bodies, or colliders, step together in a
km.fem.Scene (km.contact: implicit Euler with IPC, intersection-free; a single body with
colliders may also step symplectically, with projection). Steps: ``substeps`` equal implicit (projected Newton)
or symplectic steps per frame. The linear solver is "cholmod" or "cg" (state-only: resumed
runs repeat straight runs bit for bit; "cholmod_pcg" keeps a factor across steps).
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes.adapters import colliders as coll
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
    "friction": Field(Real(ge=0), 0.0, "Coulomb mu of every contact"),
    "dhat": Field(Real(gt=0), None, "contact barrier distance [m] (default: 1e-3 of the scene's size)"),
    "contact_tol": Field(Real(gt=0), 1e-2, "contact Newton tolerance (km.contact.Scene tol)"),
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
    "collider": coll.COLLIDER,
    "obstacle": coll.COLLIDER,
}


def dimension(solver, objects):
    return 3


class FEMSimulation(DeformableSimulation):
    NAME = "body"
    DIAGNOSTICS = ("energy", "newton_iterations")

    def __init__(self, scene):
        super().__init__(scene)
        bodies, found = coll.split(scene.config["objects"])
        if not bodies:
            raise scene.error("objects", "a fem scene needs at least one body (box or mesh)")
        made, surfaces, cells, rests, offset = [], [], [], [], 0
        for k, obj in enumerate(scene.config["objects"]):
            if obj["type"] in ("collider", "obstacle"):
                continue
            if obj["type"] == "box":
                V, T = km.fem.box_mesh(obj["lower"], obj["upper"], tuple(obj["cells"]))
            else:
                V, T = read_mesh(scene, k, obj, ("tetra",))
            try:
                made.append(km.fem.Body(V, T, model=obj["model"], youngs_modulus=obj["youngs_modulus"],
                                        poisson_ratio=obj["poisson_ratio"], density=obj["density"],
                                        fixed=fixed_vertices(V, obj["fixed"]), gravity=self.options["gravity"],
                                        damping=obj["damping"]))
            except ValueError as exc:
                raise scene.error(f"objects[{k}]", str(exc)) from None
            surfaces.append(boundary_faces(T) + offset)
            cells.append(T + offset)
            rests.append(np.array(V, float))
            offset += len(V)
        self.bodies = made
        self.surface = np.concatenate(surfaces)
        self.cells = [("tetra", np.concatenate(cells))]
        self.rest = np.concatenate(rests)
        self.rest_box = (self.rest.min(axis=0), self.rest.max(axis=0))
        self.newton = 0
        self.contact = None
        o = self.options
        if len(made) == 1 and not found:
            self.body = made[0]
            return
        self.contact = km.fem.Scene(gravity=o["gravity"], friction=o["friction"], tol=o["contact_tol"],
                                    dhat=o["dhat"] if o["dhat"] is not None else
                                    1e-3 * float(np.linalg.norm(self.rest_box[1] - self.rest_box[0])))
        try:
            for b in made:
                self.contact.add_body(b)
        except ValueError as exc:
            raise scene.error("objects", str(exc)) from None
        for k, obj in found:
            shape, kw = coll.collider_args(scene, k, obj)
            kw.pop("friction", None)
            try:
                self.contact.add_collider(shape, **kw)
            except ValueError as exc:
                raise scene.error(f"objects[{k}]", str(exc)) from None
        if o["integrator"] != "implicit":
            raise scene.error("solver.integrator", "bodies in contact step implicitly (IPC)")
        self.body = _Group(self.contact, offset)

    def _frame_box(self, lo, hi, up):
        return (lo, hi) if self.contact is None else coll.frame_box(lo, hi, self.contact, up)

    def geometry(self, axes):
        g = super().geometry(axes)
        if self.contact is not None:
            g.meshes += coll.meshes(self.contact)
        return g

    def _step(self, dt):
        o = self.options
        if self.contact is not None:
            info = self.contact.step(dt)
            self.newton = info.newton_iterations
            self.contact_info = info
        elif o["integrator"] == "symplectic":
            self.body.step(dt, "symplectic")
        else:
            info = self.body.step(dt, "implicit", tol=o["tol"], max_newton=o["max_newton"],
                                  linear_solver=o["linear_solver"])
            self.newton = info.iterations

    def diagnostics(self):
        out = {"energy": self.body.energy(), "newton_iterations": float(self.newton)}
        if self.contact is not None:  # the last step's contact diagnostics (none before the first)
            i = getattr(self, "contact_info", None)
            out.update(contact_count=float(i.contact_count) if i else 0.0,
                       min_distance=float(i.min_distance) if i else float("inf"),
                       sticking=float(i.sticking_count) if i else 0.0, sliding=float(i.sliding_count) if i else 0.0)
        return out

    # The body's own state() (its lagged factor included, so that a resumed scene is bitwise
    # the uninterrupted one), with the scene's frame counter beside it.
    def get_state(self):
        if self.contact is not None:
            c = self.contact
            return {"x": c.x[:len(self.rest)].copy(), "v": c.v[:len(self.rest)].copy(), "time": np.float64(c.time),
                    "kappa": np.float64(c._core.kappa), "steps": np.int64(self.steps)}
        state = self.body.state()
        state["solver_steps"] = state.pop("steps")
        state["steps"] = np.int64(self.steps)
        return state

    def set_state(self, state):
        state = dict(state)
        self.steps = int(state.pop("steps"))
        if self.contact is not None:
            c, start = self.contact, 0
            for b in self.bodies:
                n = len(b.x)
                b.x[...] = np.asarray(state["x"])[start:start + n]
                b.v[...] = np.asarray(state["v"])[start:start + n]
                start += n
            c._core.time = float(state["time"])
            for i, spec in enumerate(c.colliders):
                if spec["rows"] is not None:
                    c._core.x[spec["rows"]] = c.collider_positions(i)
            c._core.x[:start] = state["x"]
            c._core.v[:start] = state["v"]
            c._core.kappa = float(state["kappa"])
            return
        state["steps"] = state.pop("solver_steps")
        self.body.set_state(state)


class _Group:
    """The bodies of a contact scene seen as one: x, v (their rows, bodies first), time."""

    def __init__(self, scene, count):
        self.scene, self.count = scene, count

    x = property(lambda self: self.scene.x[:self.count])
    v = property(lambda self: self.scene.v[:self.count])
    time = property(lambda self: self.scene.time)

    def energy(self):
        s = self.scene
        return s.kinetic_energy() + s.potential_energy()


Simulation = FEMSimulation
