"""Scenes on km.mpm.Simulation: elastic solids, snow, sand and water on one background grid.

Objects: ``block`` (a box), ``sphere`` (a ball, a disk in 2D) and ``mesh`` (the interior of a
closed triangle surface in 3D or polygon of line cells in 2D, from a file meshio reads), each
filled with particles of one material on a lattice of ``ppc`` particles per cell and axis;
``collider`` (a static box or sphere with its contact condition and friction). Steps: the
solver's CFL step (``advance``).
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes import preview, regions, render3d
from kinema.scenes.adapters.base import ArrayStateSimulation, PointData, view_camera
from kinema.scenes.adapters.deformable import MESH_FIELDS, read_mesh
from kinema.scenes.schema import REGION, Field, Int, Real, Str, Table, Vec

SOLVER = Table({
    "shape": Field(Vec(item=Int(ge=2), spatial=True), doc="grid cells per axis"),
    "h": Field(Real(gt=0), doc="grid spacing [m]"),
    "origin": Field(Vec(spatial=True), None, "lower corner of the domain [m] (default 0)"),
    "boundary": Field(Str(km.mpm.BOUNDARIES), "slip", "condition at the domain walls"),
    "friction": Field(Real(ge=0), 0.0, "Coulomb friction of the walls"),
    "gravity": Field(Vec(spatial=True), None, "[m/s^2], default 9.81 down y"),
    "ppc": Field(Int(ge=1), 2, "particles per cell and axis"),
    "cfl": Field(Real(gt=0), 0.5),
})

MATERIAL_FIELDS = {
    "material": Field(Str(km.mpm.MATERIALS)),
    "density": Field(Real(gt=0), 1000.0, "[kg/m^d]"),
    "youngs_modulus": Field(Real(gt=0), None, "[Pa] (water: bulk modulus); default per material"),
    "poisson_ratio": Field(Real(), None),
    "friction_angle": Field(Real(gt=0), None, "[deg], sand"),
    "cohesion": Field(Real(ge=0), 0.0, "[Pa], sand"),
    "friction_law": Field(Str(("constant", "mu_i")), "constant", "sand: constant Drucker-Prager or mu(I)"),
    "mu_s": Field(Real(gt=0), None, "sand, mu(I): static friction coefficient"),
    "mu_2": Field(Real(gt=0), None, "sand, mu(I): limiting friction coefficient"),
    "I0": Field(Real(gt=0), None, "sand, mu(I): inertial number scale"),
    "grain_diameter": Field(Real(gt=0), None, "sand, mu(I): [m]"),
    "grain_density": Field(Real(gt=0), None, "sand, mu(I): [kg/m^d] of the grains"),
    "velocity": Field(Vec(spatial=True), None, "[m/s]"),
}

OBJECTS = {
    "block": Table({"region": Field(REGION), **MATERIAL_FIELDS}, "a box (or ball) of particles"),
    "sphere": Table({"center": Field(Vec(spatial=True)), "radius": Field(Real(gt=0)), **MATERIAL_FIELDS},
                    "a ball (disk in 2D) of particles"),
    "mesh": Table({**MESH_FIELDS, **MATERIAL_FIELDS}, "particles filling a closed mesh"),
    "collider": Table({"region": Field(REGION), "boundary": Field(Str(km.mpm.BOUNDARIES), "slip"),
                       "friction": Field(Real(ge=0), 0.0)}, "a static box or sphere"),
}

COLORS = {"elastic": (230, 90, 60), "neohookean": (240, 160, 40), "snow": (235, 240, 250),
          "sand": (200, 170, 110), "water": (50, 110, 220)}


def dimension(solver, objects):
    return len(solver["shape"])


def inside_mesh(points, vertices, cells):
    """(n,) bool: points inside a closed surface: the winding number (solid angle / 4 pi of the
    triangles, Van Oosterom and Strackee 1983) in 3D, the crossing number of the edges in 2D."""
    p = np.asarray(points, float)
    if vertices.shape[1] == 2:
        a, b = vertices[cells[:, 0]], vertices[cells[:, 1]]
        inside = np.zeros(len(p), bool)
        for s, e in zip(a, b):
            crosses = (s[1] > p[:, 1]) != (e[1] > p[:, 1])
            t = (p[:, 1] - s[1]) / np.where(e[1] != s[1], e[1] - s[1], 1.0)
            inside ^= crosses & (p[:, 0] < s[0] + t * (e[0] - s[0]))
        return inside
    winding = np.zeros(len(p))
    for chunk in range(0, len(cells), 256):
        tri = vertices[cells[chunk:chunk + 256]]  # (t, 3, 3)
        r = tri[None, :, :, :] - p[:, None, None, :]  # (n, t, 3, 3)
        ln = np.linalg.norm(r, axis=3)
        det = np.einsum("ntk,ntk->nt", r[:, :, 0], np.cross(r[:, :, 1], r[:, :, 2]))
        dots = lambda i, j: np.einsum("ntk,ntk->nt", r[:, :, i], r[:, :, j])  # noqa: E731
        den = ln[..., 0] * ln[..., 1] * ln[..., 2] + dots(0, 1) * ln[..., 2] + dots(1, 2) * ln[..., 0] + \
            dots(2, 0) * ln[..., 1]
        winding += 2 * np.arctan2(det, den).sum(axis=1)
    return np.abs(winding) > 2 * np.pi


class MPMSimulation(ArrayStateSimulation):
    DIAGNOSTICS = ("kinetic_energy", "max_speed")

    def __init__(self, scene):
        super().__init__(scene)
        o = scene.config["solver"]
        self.dim = dimension(o, None)
        self.cfl = o["cfl"]
        gravity = o["gravity"] if o["gravity"] is not None else (0.0, -9.81, 0.0)[:len(o["shape"])]
        self.sim = km.mpm.Simulation(o["shape"], o["h"], gravity=gravity, boundary=o["boundary"],
                                     origin=o["origin"], friction=o["friction"])
        self.lower = np.array(self.sim.origin, float)
        self.upper = self.lower + np.array(o["shape"]) * o["h"]
        self.spacing = o["h"] / o["ppc"]
        self.colliders = []
        for k, obj in enumerate(scene.config["objects"]):
            if obj["type"] == "collider":
                self.sim.add_collider(obj["region"], boundary=obj["boundary"], friction=obj["friction"])
                self.colliders.append(obj["region"])
                continue
            pts = self._fill(scene, k, obj)
            if len(pts) == 0:
                raise scene.error(f"objects[{k}]", f"holds no particle inside the domain at spacing {self.spacing}")
            try:
                self.sim.add_particles(pts, obj["material"], density=obj["density"],
                                       youngs_modulus=obj["youngs_modulus"], poisson_ratio=obj["poisson_ratio"],
                                       friction_angle=obj["friction_angle"], cohesion=obj["cohesion"],
                                       friction_law=obj["friction_law"], mu_s=obj["mu_s"], mu_2=obj["mu_2"],
                                       I0=obj["I0"], grain_diameter=obj["grain_diameter"],
                                       grain_density=obj["grain_density"], velocity=obj["velocity"], volume=self.spacing ** self.dim)
            except ValueError as exc:
                raise scene.error(f"objects[{k}]", str(exc)) from None
        if self.sim.count == 0:
            raise scene.error("objects", "an mpm scene needs at least one block, sphere or mesh of particles")
        self.kinds = np.array([m.kind for m in self.sim.materials])

    def _fill(self, scene, k, obj):
        """Lattice points (anchored at the domain's corner) inside the object and the domain."""
        if obj["type"] == "block":
            region = obj["region"]
        elif obj["type"] == "sphere":
            region = {"shape": "sphere", "center": obj["center"], "radius": obj["radius"]}
        else:
            kinds = ("line",) if self.dim == 2 else ("triangle",)
            vertices, cells = read_mesh(scene, k, obj, kinds)
            region = {"shape": "box", "lower": vertices.min(axis=0), "upper": vertices.max(axis=0)}
        lo, hi = regions.bounds(region)
        lo, hi = np.maximum(lo, self.lower), np.minimum(hi, self.upper)
        if np.any(hi <= lo):
            return np.zeros((0, self.dim))
        lo = self.lower + np.floor((lo - self.lower) / self.spacing) * self.spacing
        pts = km.mpm.block(lo, hi, self.spacing)
        if obj["type"] == "mesh":
            return pts[inside_mesh(pts, vertices, cells)]
        return pts[regions.contains(region, pts)]

    @property
    def time(self):
        return self.sim.time

    def advance_to(self, t_end):
        taken = self.sim.advance(t_end - self.sim.time, cfl=self.cfl)
        self.steps += taken
        return taken

    def _arrays(self):
        s = self.sim
        return {"x": s.x, "v": s.v, "F": s.F, "C": s.C, "Jp": s.Jp}

    def _core(self):
        return self.sim._sim

    def diagnostics(self):
        return {"kinetic_energy": self.sim.kinetic_energy(),
                "max_speed": float(np.linalg.norm(self.sim.v, axis=1).max())}

    def _colors(self):
        table = np.array([COLORS[k] for k in self.kinds], float)
        return table[self.sim.material]

    def _water(self):
        """Positions of the water particles (empty when the scene has none)."""
        codes = [code for code, kind in enumerate(self.kinds) if kind == "water"]
        return self.sim.x[np.isin(self.sim.material, codes)]

    def geometry(self, axes):
        """Solids, snow and sand as particles; water as its reconstructed free surface (drawn as
        water, as the SPH scenes' liquid)."""
        r = 0.5 * self.spacing
        spheres = []
        for code, kind in enumerate(self.kinds):
            if kind == "water":
                continue
            rgb = np.array(COLORS[kind]) / 255.0
            spheres.append((self.sim.x[self.sim.material == code], r, km.render.lambertian(tuple(rgb))))
        for region in self.colliders:
            if region["shape"] == "sphere":
                spheres.append((np.array([region["center"]], float), region["radius"], km.render.lambertian(0.35)))
        water = self._water()
        return render3d.Geometry(self.lower, self.upper, spheres=spheres,
                                 liquids=[(water, self.spacing)] if len(water) else [])

    def image(self, output):
        if output["render"] != "flat" and self.dim == 3:
            return render3d.image(self.geometry(output["view"] or (0, 1)), output, output["view"] or (0, 1),
                                  self.scene.error)
        cam = view_camera(output, self.dim, self.lower, self.upper, (0, 1))
        img = cam.canvas()
        for region in self.colliders:  # colliders as grey samples of their interior
            lo, hi = regions.bounds(region)
            pts = km.mpm.block(np.maximum(lo, self.lower), np.minimum(hi, self.upper), 2 * self.spacing)
            pts = pts[regions.contains(region, pts)]
            preview.splat(cam, pts, np.full((len(pts), 3), 90.0), 1.2 * self.spacing * cam.scale, img)
        return preview.splat(cam, self.sim.x, self._colors(), 0.6 * self.spacing * cam.scale, img)

    def data(self):
        s = self.sim
        items = [PointData("particles", s.x.copy(), point_data={
            "velocity": s.v.copy(), "material": s.material.astype(float), "Jp": s.Jp.copy(),
            "J": np.linalg.det(s.F)})]
        water = self._water()
        if self.dim == 3 and len(water):  # the water's free surface beside the particles (PLY/VTU)
            mesh = render3d.liquid_surface(water, self.spacing)
            if mesh is not None:
                items.append(PointData("surface", mesh.vertices, [("triangle", mesh.triangles)],
                                       surface=mesh.triangles))
        return items


Simulation = MPMSimulation
