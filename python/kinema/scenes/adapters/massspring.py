"""Scenes on km.massspring.System: cloth and spring networks (3D).

Objects, all joined into one system: ``cloth`` (km.massspring.cloth: structural, shear and
bending springs on an nx x ny grid, placed in a plane through ``origin``) and ``mesh`` (a
mesh file whose cell edges become springs), and ``collider`` (or ``obstacle``): planes, boxes,
spheres and meshes the cloth cannot pass (km.contact: implicit steps by IPC with friction,
symplectic steps by projection). Steps: ``substeps`` equal steps per frame.
The linear solver is "cholmod" or "cg": both depend on the state only, so a run resumed from
a checkpoint repeats the straight run bit for bit ("cholmod_pcg" keeps a preconditioner from
earlier steps and is left out).
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes.adapters import colliders as coll
from kinema.scenes.adapters.deformable import FIXED, MESH_FIELDS, DeformableSimulation, fixed_vertices, read_mesh
from kinema.scenes.schema import Field, Int, Real, Str, Table, Vec

SOLVER = Table({
    "integrator": Field(Str(km.massspring.INTEGRATORS), "implicit"),
    "beta": Field(Real(gt=0, le=1), 1.0, "implicit: 1 backward Euler, 0.5 trapezoid-like"),
    # Scenes resume from checkpoints bit for bit, so their default solver keeps no history:
    # "cholmod" (the library default) reuses the CHOLMOD factor of earlier steps as a PCG
    # preconditioner, which a resumed run does not have (same answer to the solver tolerance,
    # not to the last bit).
    "linear_solver": Field(Str(("cholmod_direct", "cholmod", "cg")), "cholmod_direct"),
    "substeps": Field(Int(ge=1), 1, "steps per frame"),
    "gravity": Field(Vec(spatial=True), None, "[m/s^2]"),
    "friction": Field(Real(ge=0), 0.0, "Coulomb mu against colliders and between cloth parts"),
    "dhat": Field(Real(gt=0), None, "contact barrier distance [m] (default: 1e-3 of the cloth's size)"),
})

_MATERIAL = {
    "stiffness": Field(Real(gt=0), doc="spring stiffness [N/m]"),
    "mass": Field(Real(gt=0), 1.0, "total mass [kg], spread evenly over the vertices"),
    "damping": Field(Real(ge=0), 0.0, "along-spring damping [N s/m]"),
    "fixed": FIXED,
}
OBJECTS = {
    "cloth": Table({
        "resolution": Field(Vec(2, Int(ge=2)), doc="vertices along the two sides"),
        "size": Field(Vec(2, Real(gt=0)), doc="side lengths [m]"),
        "origin": Field(Vec(spatial=True), [0.0, 0.0, 0.0], "position of vertex (0, 0) [m]"),
        "plane": Field(Str(("xy", "xz", "yz")), "xy", "the plane the cloth starts in"),
        "bending_stiffness": Field(Real(gt=0), None, "stiffness of the bending springs (default: stiffness)"),
        **_MATERIAL}, "a rectangular cloth"),
    "mesh": Table({**MESH_FIELDS, **_MATERIAL}, "a spring along every cell edge of a mesh file"),
    "collider": coll.COLLIDER,
    "obstacle": coll.COLLIDER,
}

_PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


def dimension(solver, objects):
    return 3


def _edges(cells):
    k = cells.shape[1]
    pairs = np.concatenate([cells[:, [a, b]] for a in range(k) for b in range(a + 1, k)])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _surface(cells):
    if cells.shape[1] == 3:
        return cells
    from kinema.scenes.preview import boundary_faces

    return boundary_faces(cells)


class MassSpringSimulation(DeformableSimulation):
    NAME = "cloth"
    DIAGNOSTICS = ("energy", "kinetic_energy")

    def __init__(self, scene):
        super().__init__(scene)
        o = self.options
        self.integrator, self.beta, self.solver = o["integrator"], o["beta"], o["linear_solver"]
        xs, springs, stiff, damp, mass, fixed, tris, cells = [], [], [], [], [], [], [], []
        offset = 0
        for k, obj in enumerate(scene.config["objects"]):
            if obj["type"] in ("collider", "obstacle"):
                continue
            if obj["type"] == "cloth":
                nx, ny = obj["resolution"]
                x2, s, kinds = km.massspring.cloth(nx, ny, obj["size"], dim=2, return_kinds=True)
                x = np.tile(np.asarray(obj["origin"], float), (len(x2), 1))
                a, b = _PLANES[obj["plane"]]
                x[:, a] += x2[:, 0]
                x[:, b] += x2[:, 1]
                bend = obj["bending_stiffness"] or obj["stiffness"]
                k_s = np.where(kinds == 2, bend, obj["stiffness"])
                I, J = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
                q = (I * ny + J).ravel()
                t = np.concatenate([np.stack([q, q + ny, q + ny + 1], 1), np.stack([q, q + ny + 1, q + 1], 1)])
            else:
                x, c = read_mesh(scene, k, obj, ("triangle", "tetra"))
                s = _edges(c)
                k_s = np.full(len(s), obj["stiffness"])
                t = _surface(c)
            xs.append(x)
            springs.append(s + offset)
            stiff.append(k_s)
            damp.append(np.full(len(s), obj["damping"]))
            mass.append(np.full(len(x), obj["mass"] / len(x)))
            fixed.append(fixed_vertices(x, obj["fixed"]) + offset)
            tris.append(t + offset)
            offset += len(x)
        if not xs:
            raise scene.error("objects", 'a massspring scene needs an object of type "cloth" or "mesh"')
        x = np.concatenate(xs)
        self.body = km.massspring.System(x, np.concatenate(springs), stiffness=np.concatenate(stiff),
                                         mass=np.concatenate(mass), damping=np.concatenate(damp),
                                         fixed=np.concatenate(fixed), gravity=o["gravity"])
        self.surface = np.concatenate(tris)
        self.cells = [("triangle", self.surface)]
        self.rest = x.copy()
        self.rest_box = (x.min(axis=0), x.max(axis=0))
        self.contact = None
        _, found = coll.split(scene.config["objects"])
        if found:
            self.contact = km.contact.attach(self.body, triangles=self.surface, friction=o["friction"], dhat=o["dhat"])
            for k, obj in found:
                shape, kw = coll.collider_args(scene, k, obj)
                try:
                    self.body.add_collider(shape, **kw)
                except ValueError as exc:
                    raise scene.error(f"objects[{k}]", str(exc)) from None
            if self.integrator != "implicit":
                try:
                    self.contact._shapes()  # the colliders of the symplectic projection, checked now
                except ValueError as exc:
                    raise scene.error("solver.integrator", str(exc)) from None

    def _frame_box(self, lo, hi, up):
        return (lo, hi) if self.contact is None else coll.frame_box(lo, hi, self.contact.scene(), up)

    def geometry(self, axes):
        g = super().geometry(axes)
        if self.contact is not None and self.integrator == "implicit":
            g.meshes += coll.meshes(self.contact.scene())
        return g

    def _step(self, dt):
        self.last = self.body.step(dt, self.integrator, self.beta, linear_solver=self.solver)

    def diagnostics(self):
        out = {"energy": self.body.energy(), "kinetic_energy": self.body.kinetic_energy()}
        if self.contact is not None:  # the last step's contact diagnostics (none before the first)
            i = getattr(self, "last", None)
            out.update(contact_count=float(i.contact_count) if i else 0.0,
                       min_distance=float(i.min_distance) if i else float("inf"))
            if self.integrator == "implicit":
                out.update(sticking=float(i.sticking_count) if i else 0.0,
                           sliding=float(i.sliding_count) if i else 0.0)
        return out


Simulation = MassSpringSimulation
