"""Scenes on km.nbody.System: self-gravitating particles (leapfrog, FMM gravity).

Objects: ``plummer`` (a Plummer sphere in virial equilibrium, km.nbody.plummer, moved to
``center`` with bulk ``velocity``). Two spheres with velocities of a parabolic encounter make
a galaxy collision. Steps: ``substeps`` equal kick-drift-kick steps per frame.
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes import preview
from kinema.scenes.adapters.base import PointData, SubstepSimulation, restore, view_camera
from kinema.scenes.schema import Field, Int, Real, Table, Vec

SOLVER = Table({
    "substeps": Field(Int(ge=1), 4, "leapfrog steps per frame"),
    "G": Field(Real(gt=0), 1.0, "gravitational constant"),
    "softening": Field(Real(ge=0), 0.05, "Plummer softening length [m]"),
    "eps": Field(Real(gt=0, le=0.1), 1e-6, "relative accuracy of the FMM far field"),
})

OBJECTS = {
    "plummer": Table({
        "center": Field(Vec(spatial=True)),
        "velocity": Field(Vec(spatial=True), None, "bulk velocity [m/s] (default 0)"),
        "particles": Field(Int(ge=2), 2000),
        "mass": Field(Real(gt=0), 1.0, "total mass [kg]"),
        "scale": Field(Real(gt=0), 1.0, "Plummer radius [m]"),
        "seed": Field(Int(ge=0), 0),
    }, "a Plummer sphere in virial equilibrium"),
}


def dimension(solver, objects):
    return 3


class NBodySimulation(SubstepSimulation):
    DIAGNOSTICS = ("energy_drift", "momentum_drift", "virial_ratio")

    def __init__(self, scene):
        super().__init__(scene)
        self.dim = 3
        o = scene.config["solver"]
        self.substeps = o["substeps"]
        xs, vs, ms = [], [], []
        for obj in scene.config["objects"]:
            x, v, m = km.nbody.plummer(obj["particles"], seed=obj["seed"], G=o["G"],
                                       total_mass=obj["mass"], scale=obj["scale"])
            xs.append(x + obj["center"])
            vs.append(v + (obj["velocity"] if obj["velocity"] is not None else 0.0))
            ms.append(m)
        if not xs:
            raise scene.error("objects", 'an nbody scene needs an object of type "plummer"')
        self.sim = km.nbody.System(np.concatenate(xs), np.concatenate(vs), np.concatenate(ms),
                                   G=o["G"], softening=o["softening"], eps=o["eps"])
        self.e0 = self.sim.energy()
        self.p0 = self.sim.momentum()
        lo, hi = self.sim.x.min(axis=0), self.sim.x.max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.3 * (hi - lo).max()
        self.view = (centre - half, centre + half)

    def set_state(self, state):
        restore(self.sim.x, state["x"], "x")
        restore(self.sim.v, state["v"], "v")
        super().set_state(state)

    def diagnostics(self):
        return {"energy_drift": abs(self.sim.energy() / self.e0 - 1),
                "momentum_drift": float(np.linalg.norm(self.sim.momentum() - self.p0)),
                "virial_ratio": self.sim.virial_ratio()}

    def image(self, output):
        cam = view_camera(output, 3, *self.view, (0, 1))
        speed = np.linalg.norm(self.sim.v, axis=1)
        lo, hi = output["range"] or (0.0, max(float(np.percentile(speed, 99)), 1e-12))
        colors = preview.colormap(speed, output["colormap"], lo, hi).astype(float)
        return preview.splat(cam, self.sim.x, colors, 1.0)

    def data(self):
        return [PointData("bodies", self.sim.x.copy(),
                          point_data={"velocity": self.sim.v.copy(), "mass": self.sim.mass.copy()})]


Simulation = NBodySimulation
