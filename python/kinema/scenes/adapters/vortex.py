"""Scenes on km.vortex.VortexParticles: 2D vortex-particle flows (RK4, FMM velocities).

Objects: ``patch`` (a Gaussian vortex patch, km.vortex.merging_patches' disc) and ``sheet``
(a flat vortex sheet with the elliptic circulation Gamma(s) = Gamma0 sqrt(1 - s^2) of a loaded
wing, which rolls up at its tips: Krasny 1987, "Computation of vortex sheet roll-up in the
Trefftz plane", J. Fluid Mech. 184). Steps: ``substeps`` equal RK4 steps per frame.
In 3D (km.vortex.VortexParticles3D): ``ring`` (a vortex ring, km.vortex.ring); a scene with
rings is a 3D scene and takes no 2D objects.
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes import preview
from kinema.scenes.adapters.base import PointData, SubstepSimulation, restore, view_camera
from kinema.scenes.adapters.base import Simulation as BaseSimulation
from kinema.scenes.schema import Field, Int, Real, Table, Vec

SOLVER = Table({
    "substeps": Field(Int(ge=1), 2, "RK4 steps per frame"),
    "eps": Field(Real(gt=0, le=0.1), 1e-8, "relative accuracy of the FMM velocities"),
    "core": Field(Real(gt=0), None, "core radius [m] (default: the largest the objects suggest)"),
})

OBJECTS = {
    "patch": Table({
        "center": Field(Vec(spatial=True)),
        "radius": Field(Real(gt=0), doc="[m]; the Gaussian's width is radius / 2"),
        "particles": Field(Int(ge=10), 2000),
        "circulation": Field(Real(), 1.0, "total circulation [m^2/s]"),
        "seed": Field(Int(ge=0), 0, "of the lattice jitter"),
    }, "a Gaussian vortex patch"),
    "sheet": Table({
        "center": Field(Vec(spatial=True)),
        "half_span": Field(Real(gt=0), 1.0, "[m]"),
        "particles": Field(Int(ge=4), 200),
        "circulation": Field(Real(), 1.0, "Gamma0, the circulation at the middle [m^2/s]"),
    }, "an elliptically loaded vortex sheet along x"),
    "ring": Table({
        "center": Field(Vec(spatial=True)),
        "axis": Field(Vec(3), [0.0, 0.0, 1.0], "direction of travel (for positive circulation)"),
        "radius": Field(Real(gt=0), 1.0, "[m]"),
        "particles": Field(Int(ge=8), 100),
        "circulation": Field(Real(), 1.0, "[m^2/s]"),
    }, "a 3D vortex ring (core radius: solver.core, default 0.1 radius)"),
}


def dimension(solver, objects):
    return 3 if any(o["type"] == "ring" for o in objects) else 2


def _sheet(obj):
    """Points at the midpoints (in angle) of a cosine spacing of [-1, 1], each carrying the
    circulation Gamma(s_j) - Gamma(s_j+1) of its stretch of sheet (Krasny 1987, Sec. 3)."""
    n = obj["particles"]
    alpha = np.linspace(0, np.pi, n + 1)
    gamma = obj["circulation"] * np.sin(alpha)  # Gamma(s) at s = -cos(alpha)
    mid = 0.5 * (alpha[1:] + alpha[:-1])
    x = np.stack([-np.cos(mid) * obj["half_span"], np.zeros(n)], 1) + obj["center"]
    # Roll-up needs overlapping cores; Krasny used delta = 0.05 span for n = 200 or more.
    return x, gamma[:-1] - gamma[1:], 0.05 * obj["half_span"]


class VortexSimulation(SubstepSimulation):
    DIAGNOSTICS = ("circulation_drift", "impulse_drift")

    def __init__(self, scene):
        super().__init__(scene)
        self.dim = 2
        o = scene.config["solver"]
        self.substeps = o["substeps"]
        xs, gs, cores = [], [], []
        for obj in scene.config["objects"]:
            if obj["type"] == "patch":
                # merging_patches builds two discs at +-separation/2: with 0 the first is centred.
                x, g, core = km.vortex.merging_patches(obj["particles"], 0.0, obj["radius"], seed=obj["seed"])
                half = len(x) // 2
                x, g = x[:half] + obj["center"], g[:half] * obj["circulation"]
            else:
                x, g, core = _sheet(obj)
            xs.append(x)
            gs.append(g)
            cores.append(core)
        if not xs:
            raise scene.error("objects", 'a vortex scene needs an object of type "patch" or "sheet"')
        self.sim = km.vortex.VortexParticles(np.concatenate(xs), np.concatenate(gs), o["core"] or max(cores),
                                             eps=o["eps"])
        self.gamma0 = self.sim.total_circulation()
        self.impulse0 = self.sim.linear_impulse()
        x0 = self.sim.x
        lo, hi = x0.min(axis=0), x0.max(axis=0)
        grow = 0.5 * (hi - lo).max()
        self.view = (lo - grow, hi + grow)

    def get_state(self):
        return {"x": self.sim.x.copy(), "time": np.float64(self.sim.time), "steps": np.int64(self.steps)}

    def set_state(self, state):
        restore(self.sim.x, state["x"], "x")
        self.sim.time = float(state["time"])
        self.steps = int(state["steps"])

    def diagnostics(self):
        return {"circulation_drift": abs(self.sim.total_circulation() - self.gamma0),
                "impulse_drift": float(np.linalg.norm(self.sim.linear_impulse() - self.impulse0))}

    def image(self, output):
        cam = view_camera(output, 2, *self.view, (0, 1))
        g = self.sim.circulation
        lim = float(np.abs(g).max()) or 1.0
        lo, hi = output["range"] or (-lim, lim)
        colors = preview.colormap(g, output["colormap"], lo, hi).astype(float)
        return preview.splat(cam, self.sim.x, colors, 1.2)

    def data(self):
        return [PointData("vortices", self.sim.x.copy(), point_data={"circulation": self.sim.circulation})]


class Vortex3DSimulation(SubstepSimulation):
    DIAGNOSTICS = ("impulse_drift",)

    def __init__(self, scene):
        super().__init__(scene)
        self.dim = 3
        o = scene.config["solver"]
        self.substeps = o["substeps"]
        objects = scene.config["objects"]
        if any(obj["type"] != "ring" for obj in objects):
            raise scene.error("objects", 'a 3D vortex scene (with rings) takes only objects of type "ring"')
        core = o["core"] or 0.1 * min(obj["radius"] for obj in objects)
        xs, alphas = zip(*(km.vortex.ring(obj["radius"], core, obj["circulation"], obj["particles"],
                                          center=obj["center"], axis=obj["axis"]) for obj in objects))
        self.sim = km.vortex.VortexParticles3D(np.concatenate(xs), np.concatenate(alphas), core, eps=o["eps"])
        self.ring_of = np.concatenate([np.full(len(x), k) for k, x in enumerate(xs)])
        self.core = core
        self.ring_radius = max(obj["radius"] for obj in objects)
        self.impulse0 = self.sim.linear_impulse()
        x0 = self.sim.x
        lo, hi = x0.min(axis=0), x0.max(axis=0)
        grow = 0.6 * (hi - lo).max()
        self.view = (lo - grow, hi + grow)

    def diagnostics(self):
        return {"impulse_drift": float(np.linalg.norm(self.sim.linear_impulse() - self.impulse0))}

    #: Colours of the rings in a "preview"/"pathtrace" frame, in the order of the scene's objects.
    RING_COLOURS = ((0.95, 0.55, 0.15), (0.2, 0.55, 0.95), (0.35, 0.8, 0.35), (0.85, 0.3, 0.6))

    def image(self, output):
        if output["render"] != "flat":
            return self._image_3d(output)
        cam = view_camera(output, 3, *self.view, (0, 2))
        w = np.linalg.norm(self.sim.strength, axis=1)
        lo, hi = output["range"] or (0.0, float(w.max()) or 1.0)
        colors = preview.colormap(w, output["colormap"], lo, hi).astype(float)
        return preview.splat(cam, self.sim.x, colors, 1.5)

    def _image_3d(self, output):
        """The rings as tubes of shaded spheres (radius half the core) in perspective, one colour
        per ring, seen obliquely from a camera that follows their centroid (they travel)."""
        from kinema.scenes import render3d

        x = self.sim.x
        centre = x.mean(axis=0)
        travel = self.sim.linear_impulse()
        axis = travel / np.linalg.norm(travel) if np.linalg.norm(travel) > 0 else np.array([0.0, 0.0, 1.0])
        side = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        up = np.cross(side, axis)
        eye = centre + self.ring_radius * (3.2 * side + 1.6 * up + 1.2 * axis)
        width = output["width"]
        height = output["height"] or round(0.6 * width)
        cam = km.render.Camera(tuple(eye), tuple(centre), tuple(up), 40.0, width=width, height=height)
        scene = km.render.Scene()
        for k in range(int(self.ring_of.max()) + 1):
            colour = self.RING_COLOURS[k % len(self.RING_COLOURS)]
            scene.add_spheres(x[self.ring_of == k], 0.5 * self.core, km.render.lambertian(colour))
        sky = render3d.NIGHT_SKY
        if output["render"] == "pathtrace":
            linear = scene.render(cam, spp=output["spp"], max_depth=output["max_depth"], seed=output["seed"], sky=sky)
        else:
            linear = scene.preview(cam, sky=sky, light=tuple(up + 0.5 * side + 0.3 * axis), ambient=0.25,
                                   specular=0.35, shininess=48.0)
        return km.render.tone_map(linear)

    def data(self):
        return [PointData("vortices", self.sim.x.copy(), point_data={"strength": self.sim.strength.copy()})]


class Simulation(BaseSimulation):
    """The 2D or the 3D simulation, as the scene's objects ask (a scene with rings is 3D)."""

    DIAGNOSTICS = VortexSimulation.DIAGNOSTICS
    PERSPECTIVE = True  # 3D scenes (rings) draw "preview"/"pathtrace" frames of their own

    def __new__(cls, scene):
        return Vortex3DSimulation(scene) if scene.dim == 3 else VortexSimulation(scene)
