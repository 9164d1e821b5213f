"""Scenes on km.sph.Fluid: SPH liquids (WCSPH or DFSPH, 2D or 3D) in a tank with obstacles.

Objects: ``fluid`` (a region filled with particles on the lattice of the solver's spacing, with
an initial velocity) and ``obstacle`` (a solid region sampled as a shell of boundary particles
two spacings thick, Akinci et al. 2012). Steps: the solver's CFL step (``advance``).
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes import preview, regions, render3d
from kinema.scenes.adapters.base import PointData, Simulation, view_camera
from kinema.scenes.schema import REGION, Bool, Field, Int, Real, Str, Table, Vec

SOLVER = Table({
    "method": Field(Str(km.sph.METHODS), "dfsph"),
    "spacing": Field(Real(gt=0), doc="particle spacing [m] (support radius 2 spacing)"),
    "domain": Field(Table({"lower": Field(Vec(spatial=True)), "upper": Field(Vec(spatial=True))}),
                    doc="the closed tank [m]"),
    "rho0": Field(Real(gt=0), 1000.0, "rest density [kg/m^d]"),
    "viscosity": Field(Real(ge=0), 0.0, "kinematic viscosity [m^2/s]"),
    "gravity": Field(Vec(spatial=True), None, "[m/s^2]; none by default"),
    "speed_of_sound": Field(Real(gt=0), None, "WCSPH c [m/s]"),
    "gamma": Field(Real(gt=0), 7.0),
    "tol": Field(Real(gt=0), 1e-3, "DFSPH mean density error"),
    "divergence_tol": Field(Real(gt=0), 1e-3),
    "max_iter": Field(Int(ge=1), 100),
    "divergence_solve": Field(Bool(), True),
    "reorder_every": Field(Int(ge=0), 16, "steps between Morton reorderings"),
    "cfl": Field(Real(gt=0), 0.4),
})

OBJECTS = {
    "fluid": Table({"region": Field(REGION), "velocity": Field(Vec(spatial=True), None, "[m/s]")},
                   "particles filling the region"),
    "obstacle": Table({"region": Field(REGION)}, "a static solid (boundary samples)"),
}


def dimension(solver, objects):
    return len(solver["domain"]["lower"])


def _lattice(region, spacing, lower, upper):
    """Points of the lattice anchored at the tank's lower corner (first point half a spacing
    in) that lie in the region, clipped to [lower, upper]."""
    lo, hi = regions.bounds(region)
    lo, hi = np.maximum(lo, lower), np.minimum(hi, upper)
    if np.any(hi <= lo):
        return np.zeros((0, len(lo)))
    # Snap the box to the tank's lattice so that blocks and walls line up.
    lo = lower + np.floor((lo - lower) / spacing) * spacing
    pts = km.sph.block(lo, hi, spacing)
    return pts[regions.contains(region, pts)]


def _shell(region, spacing):
    """Boundary samples of a solid region: its lattice points within two spacings of its surface."""
    lo, hi = regions.bounds(region)
    pts = km.sph.block(lo, hi, spacing)
    inside = regions.contains(region, pts)
    pts = pts[inside]
    if region["shape"] == "box":
        depth = np.minimum(pts - lo, hi - pts).min(axis=1)
    else:
        depth = region["radius"] - np.linalg.norm(pts - region["center"], axis=1)
    return pts[depth < 2 * spacing]


class SPHSimulation(Simulation):
    DIAGNOSTICS = ("density_error", "kinetic_energy", "max_speed")

    def __init__(self, scene):
        super().__init__(scene)
        o = scene.config["solver"]
        self.dim = dimension(o, None)
        self.spacing, self.cfl = o["spacing"], o["cfl"]
        self.lower = np.array(o["domain"]["lower"])
        self.upper = np.array(o["domain"]["upper"])
        fluid, vel, solid = [], [], []
        for k, obj in enumerate(scene.config["objects"]):
            if obj["type"] == "fluid":
                pts = _lattice(obj["region"], self.spacing, self.lower, self.upper)
                if len(pts) == 0:
                    raise scene.error(f"objects[{k}].region", "holds no particle inside the domain "
                                      f"at spacing {self.spacing}")
                fluid.append(pts)
                vel.append(np.tile(obj["velocity"] or np.zeros(self.dim), (len(pts), 1)))
            else:
                solid.append(_shell(obj["region"], self.spacing))
        if not fluid:
            raise scene.error("objects", 'an sph scene needs at least one object of type "fluid"')
        x = np.concatenate(fluid)
        if solid:  # fluid particles inside an obstacle are dropped
            keep = np.ones(len(x), bool)
            for obj in scene.config["objects"]:
                if obj["type"] == "obstacle":
                    keep &= ~regions.contains(obj["region"], x)
            x, vel = x[keep], [np.concatenate(vel)[keep]]
        self.obstacles = np.concatenate(solid) if solid else np.zeros((0, self.dim))
        self.fluid = km.sph.Fluid(
            x, self.spacing, method=o["method"], rho0=o["rho0"], viscosity=o["viscosity"], gravity=o["gravity"],
            domain=(self.lower, self.upper), boundary=self.obstacles if solid else None,
            speed_of_sound=o["speed_of_sound"], gamma=o["gamma"], velocity=np.concatenate(vel), tol=o["tol"],
            divergence_tol=o["divergence_tol"], max_iter=o["max_iter"], divergence_solve=o["divergence_solve"],
            reorder_every=o["reorder_every"])

    @property
    def time(self):
        return self.fluid.time

    def advance_to(self, t_end):
        taken = self.fluid.advance(t_end - self.fluid.time, cfl=self.cfl)
        self.steps += taken
        return taken

    def get_state(self):
        # The fluid's state holds what its steps carry over (neighbour lists, warm start), so a
        # resumed run takes bit for bit the steps of a straight one.
        return self.fluid.state() | {"scene_steps": np.int64(self.steps)}

    def set_state(self, state):
        if "scene_steps" not in state:
            raise ValueError("checkpoint: missing 'scene_steps'")
        self.fluid.set_state({k: v for k, v in state.items() if k != "scene_steps"})
        self.steps = int(state["scene_steps"])

    def diagnostics(self):
        f = self.fluid
        return {"density_error": f.density_error(), "kinetic_energy": f.kinetic_energy(),
                "max_speed": float(np.linalg.norm(f.v, axis=1).max())}

    WATER = km.render.lambertian((0.15, 0.4, 0.8))
    SOLID = km.render.lambertian(0.6)

    def geometry(self, axes):
        """The water's free surface (km.surface) in the tank's frame, the obstacles as solids."""
        boxes, balls = [], []
        for obj in self.scene.config["objects"]:
            region = obj["region"]
            if obj["type"] == "obstacle" and region["shape"] == "box":
                boxes.append((region["lower"], region["upper"], self.SOLID))
            elif obj["type"] == "obstacle":
                balls.append((np.atleast_2d(region["center"]), region["radius"], self.SOLID))
        return render3d.Geometry(self.lower, self.upper, spheres=balls, boxes=boxes,
                                 liquids=[(self.fluid.x, self.spacing)], tank=True)

    def image(self, output):
        if output["render"] != "flat":
            axes = output["view"] or (0, 1)
            return render3d.image(self.geometry(axes), output, axes, self.scene.error)
        cam = view_camera(output, self.dim, self.lower, self.upper, (0, 1))
        img = cam.canvas()
        if len(self.obstacles):
            preview.splat(cam, self.obstacles, np.full((len(self.obstacles), 3), 120.0),
                          0.6 * self.spacing * cam.scale, img)
        speed = np.linalg.norm(self.fluid.v, axis=1)
        lo, hi = output["range"] or (0.0, max(float(speed.max()), 1e-12))
        colors = preview.colormap(speed, output["colormap"], lo, hi).astype(float)
        return preview.splat(cam, self.fluid.x, colors, 0.6 * self.spacing * cam.scale, img)

    def data(self):
        f = self.fluid
        items = [PointData("fluid", f.x.copy(), point_data={"velocity": f.v.copy(), "density": f.density.copy()},
                           ids=f.ids.copy())]
        if self.steps == 0 and len(self.obstacles):
            items.append(PointData("obstacles", self.obstacles))
        if self.dim == 3:  # the free surface beside the particles (a PLY of triangles)
            mesh = render3d.liquid_surface(f.x, self.spacing)
            if mesh is not None:
                items.append(PointData("surface", mesh.vertices, [("triangle", mesh.triangles)], surface=mesh.triangles))
        return items


Simulation = SPHSimulation
