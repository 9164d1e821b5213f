"""Scenes on km.grid.Fluid: smoke and incompressible flow on a MAC grid (2D or 3D).

Objects: ``obstacle`` (solid cells in a region), ``source`` (density/temperature/velocity
imposed in a region before every step), ``block`` (initial density/temperature/velocity in a
region) and ``wall`` (a moving no-slip wall). Time steps: km.grid.Fluid.stable_dt (the CFL rule
of Bridson 2015, Sec. 3.2), at most ``max_dt``, ending exactly on each frame.
"""

from __future__ import annotations

import numpy as np

import kinema as km
from kinema.scenes import preview, regions, render3d
from kinema.scenes.adapters.base import GridData, Simulation
from kinema.scenes.schema import REGION, Bool, Field, Int, ListOf, Real, Str, Table, Vec

SOLVER = Table({
    "resolution": Field(Vec(item=Int(ge=1), spatial=True), doc="cells per axis"),
    "size": Field(Real(gt=0), 1.0, "domain length along x [m]; h = size / resolution[0]"),
    "advection": Field(Str(km.grid.SCHEMES), "maccormack"),
    "rk_order": Field(Int(ge=1), 2),
    "projection": Field(Str(("mgpcg", "multigrid", "cg")), "mgpcg"),
    "tol": Field(Real(gt=0, le=0.5), 1e-6, "relative residual of the pressure solve"),
    "viscosity": Field(Real(ge=0), 0.0, "kinematic viscosity [m^2/s]"),
    "boundary": Field(Str(("closed", "periodic")), "closed"),
    "walls": Field(Str(("free_slip", "no_slip")), "free_slip"),
    "open": Field(ListOf(Str(("x-", "x+", "y-", "y+", "z-", "z+"))), [],
                  "open (outflow) sides: p = 0 there, smoke leaves the box"),
    "gravity": Field(Vec(spatial=True), None, "[m/s^2]"),
    "density": Field(Bool(), False, "carry a smoke density field"),
    "temperature": Field(Bool(), False, "carry a temperature field"),
    "buoyancy": Field(Vec(2), [0.0, 0.0], "(alpha, beta): force (-alpha density + beta T) up"),
    "vorticity_confinement": Field(Real(ge=0), 0.0),
    "cfl": Field(Real(gt=0), 1.0, "CFL number of the adaptive step"),
    "max_dt": Field(Real(gt=0), 1.0 / 60, "largest step [s]"),
})

_VALUES = {
    "region": Field(REGION),
    "density": Field(Real(), None, "smoke density"),
    "temperature": Field(Real(), None),
    "velocity": Field(Vec(spatial=True), None, "[m/s]"),
}
OBJECTS = {
    "obstacle": Table({"region": Field(REGION)}, "solid cells (zero velocity on their faces)"),
    "source": Table(_VALUES, "values imposed in the region before every step"),
    "block": Table(_VALUES, "initial values in the region"),
    "wall": Table({"side": Field(Str(("x-", "x+", "y-", "y+", "z-", "z+"))),
                   "velocity": Field(Vec(spatial=True), doc="tangential wall velocity [m/s]")},
                  "a moving no-slip wall (needs viscosity > 0 to drag the fluid)"),
}

FIELDS = ("density", "temperature", "speed", "pressure", "vorticity")


def dimension(solver, objects):
    return len(solver["resolution"])


class GridSimulation(Simulation):
    DIAGNOSTICS = ("kinetic_energy", "max_divergence", "smoke_mass")

    def __init__(self, scene):
        super().__init__(scene)
        o = scene.config["solver"]
        shape = tuple(o["resolution"])
        self.dim, self.h = len(shape), o["size"] / shape[0]
        self.cfl, self.max_dt = o["cfl"], o["max_dt"]
        self.fluid = km.grid.Fluid(
            shape, self.h, advection=o["advection"], rk_order=o["rk_order"], projection=o["projection"],
            tol=o["tol"], viscosity=o["viscosity"], boundary=o["boundary"], walls=o["walls"],
            gravity=o["gravity"], density=o["density"], temperature=o["temperature"],
            buoyancy=tuple(o["buoyancy"]), vorticity_confinement=o["vorticity_confinement"],
            open=tuple(o["open"]))
        centres = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) * self.h for n in shape], indexing="ij"), -1)
        centres = centres.reshape(-1, self.dim)
        for k, obj in enumerate(scene.config["objects"]):
            kind = obj["type"]
            if kind == "obstacle":
                self.fluid.solid |= regions.contains(obj["region"], centres).reshape(shape)
            elif kind == "wall":
                self.fluid.set_wall_velocity(obj["side"], obj["velocity"])
            else:
                cells = regions.contains(obj["region"], centres).reshape(shape)
                for name in ("density", "temperature"):
                    if obj[name] is not None and not o[name]:
                        raise scene.error(f"objects[{k}].{name}", f"the solver carries no {name} field; "
                                          f"set solver.{name} = true")
                if kind == "source":
                    if all(obj[name] is None for name in ("density", "temperature", "velocity")):
                        continue
                    self.fluid.add_source(cells, density=obj["density"], temperature=obj["temperature"],
                                          velocity=obj["velocity"])
                else:
                    self._impose(cells, obj)

    def _impose(self, cells, obj):
        """The initial values of a ``block`` object."""
        f = self.fluid
        for name in ("density", "temperature"):
            if obj[name] is not None:
                getattr(f, name)[cells] = obj[name]
        if obj["velocity"] is not None:
            # Every face of a cell in the region takes the velocity component normal to it.
            for axis, comp in enumerate(f.velocity):
                faces = np.zeros(comp.shape, bool)
                lo = [slice(0, n) for n in cells.shape]
                hi = list(lo)
                hi[axis] = slice(1, cells.shape[axis] + 1)
                faces[tuple(lo)] |= cells
                faces[tuple(hi)] |= cells
                comp[faces] = obj["velocity"][axis]

    @property
    def time(self):
        return self.fluid.time

    def advance_to(self, t_end):
        taken = self.fluid.advance(max(t_end - self.fluid.time, 0.0), self.cfl, max_dt=self.max_dt)
        self.steps += taken
        return taken

    def get_state(self):
        return self.fluid.state() | {"scene_steps": np.int64(self.steps)}

    def set_state(self, state):
        self.fluid.set_state(state)
        self.steps = int(state["scene_steps"])

    def diagnostics(self):
        f = self.fluid
        d = {"kinetic_energy": f.kinetic_energy(), "max_divergence": float(np.abs(f.divergence()).max())}
        d["smoke_mass"] = float(f.density.sum() * self.h**self.dim) if self.scene.config["solver"]["density"] \
            else 0.0
        return d

    def _cell_velocity(self):
        f = self.fluid
        comps = []
        for axis, c in enumerate(f.velocity):
            lo = [slice(None)] * self.dim
            hi = list(lo)
            lo[axis], hi[axis] = slice(0, -1), slice(1, None)
            comps.append(0.5 * (c[tuple(lo)] + c[tuple(hi)]))
        return np.stack(comps, axis=-1)

    def field(self, name):
        if name in ("density", "temperature"):
            if not self.scene.config["solver"][name]:
                raise self.scene.error("output.field", f"the solver carries no {name} field")
            return getattr(self.fluid, name)
        if name == "pressure":
            return self.fluid.pressure
        vel = self._cell_velocity()
        if name == "speed":
            return np.linalg.norm(vel, axis=-1)
        g = [np.gradient(vel[..., c], self.h, axis=a) for c in range(self.dim) for a in range(self.dim)]
        if self.dim == 2:
            return g[2] - g[1]  # dv/dx - du/dy
        return np.sqrt((g[7] - g[5]) ** 2 + (g[2] - g[6]) ** 2 + (g[3] - g[1]) ** 2)

    def image(self, output):
        name = output["field"] or ("density" if self.scene.config["solver"]["density"] else "speed")
        if name not in FIELDS:
            raise self.scene.error("output.field", f"expected one of {', '.join(FIELDS)} for a grid scene, "
                                   f"got {name!r}")
        q = self.field(name)
        solid = self.fluid.solid
        if self.dim == 3:  # ray-marched (render3d.smoke_image), over the floor and the solids
            obstacles = [o["region"] for o in self.scene.config["objects"] if o["type"] == "obstacle"]
            return render3d.smoke_image(q, self.h, output, obstacles, self.scene.error)
        lo, hi = output["range"] or (None, None)
        return preview.field_image(q, cmap=output["colormap"], vmin=lo, vmax=hi, mask=solid,
                                   width=output["width"])

    def data(self):
        fields = {"pressure": np.asarray(self.fluid.pressure)}
        for name in ("density", "temperature"):
            if self.scene.config["solver"][name]:
                fields[name] = np.asarray(getattr(self.fluid, name))
        fields["velocity"] = self._cell_velocity()
        fields["solid"] = self.fluid.solid.astype(float)
        return [GridData("grid", fields, self.h)]


Simulation = GridSimulation
