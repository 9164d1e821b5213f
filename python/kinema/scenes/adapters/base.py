"""What every solver adapter provides to the scene runner (see adapters/__init__.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinema.scenes import preview


@dataclass
class GridData:
    """Cell-centred fields (name -> [i, j(, k)] or [i, j(, k), c]) on cells of size h: a .vti."""

    name: str
    fields: dict
    h: float


@dataclass
class PointData:
    """Points (n, d) with optional cells [(meshio type, indices)], per-point data and the
    surface triangles a PLY file holds: a .vtu and a .ply (kinema.io). ids: the input index of
    each row, when the solver reorders its particles (written in input order)."""

    name: str
    points: np.ndarray
    cells: list = field(default_factory=list)
    point_data: dict = field(default_factory=dict)
    surface: np.ndarray | None = None
    ids: np.ndarray | None = None


class Simulation:
    """A solver built from a scene. Subclasses set ``self.dim`` and implement the methods."""

    #: names of :meth:`diagnostics` (a scene's ``metric`` must be one of them)
    DIAGNOSTICS: tuple = ()

    def __init__(self, scene):
        self.scene = scene
        self.steps = 0  # solver steps taken (substeps of the frames)

    @property
    def time(self) -> float:
        raise NotImplementedError

    def advance_to(self, t_end) -> int:
        """Advances to simulated time ``t_end`` [s]; returns the number of solver steps."""
        raise NotImplementedError

    def get_state(self) -> dict:
        """Every evolving quantity (copies): what a checkpoint must hold to continue exactly."""
        raise NotImplementedError

    def set_state(self, state):
        """Restores :meth:`get_state`'s dict into a simulation built from the same scene."""
        raise NotImplementedError

    def diagnostics(self) -> dict:
        return {}

    def image(self, output):
        """The preview frame: an (H, W, 3) uint8 image about ``output["width"]`` pixels wide."""
        raise NotImplementedError

    def data(self) -> list:
        """The frame's data files: GridData and PointData items."""
        return []


class SubstepSimulation(Simulation):
    """A simulation ``self.sim`` advanced by ``self.substeps`` equal steps per frame, whose
    ``state()`` / ``set_state()`` hold everything it evolves (km.nbody, km.vortex)."""

    @property
    def time(self):
        return self.sim.time

    def advance_to(self, t_end):
        dt = (t_end - self.sim.time) / self.substeps
        for _ in range(self.substeps):
            self.sim.step(dt)
        self.steps += self.substeps
        return self.substeps

    def get_state(self):
        return self.sim.state() | {"scene_steps": np.int64(self.steps)}

    def set_state(self, state):
        self.sim.set_state(state)
        self.steps = int(state["scene_steps"])


class ArrayStateSimulation(Simulation):
    """A simulation whose state is a set of writable views of the C++ solver's arrays plus its
    time and step counter (restored through the bindings' setters)."""

    STEP_ATTR = "steps"  # the step counter's name on the C++ object

    def _arrays(self) -> dict:
        """name -> writable view of every evolving array."""
        raise NotImplementedError

    def _core(self):
        """The C++ object holding ``time`` and the step counter."""
        raise NotImplementedError

    def get_state(self):
        core = self._core()
        state = {k: v.copy() for k, v in self._arrays().items()}
        state.update(time=np.float64(core.time), solver_steps=np.int64(getattr(core, self.STEP_ATTR)),
                     steps=np.int64(self.steps))
        return state

    def set_state(self, state):
        for name, view in self._arrays().items():
            restore(view, state[name], name)
        core = self._core()
        core.time = float(state["time"])
        setattr(core, self.STEP_ATTR, int(state["solver_steps"]))
        self.steps = int(state["steps"])


def restore(view, value, name):
    """Writes a saved array into a solver's state view, checking that the shapes agree."""
    value = np.asarray(value)
    if view.shape != value.shape:
        raise ValueError(f"checkpoint: {name} has shape {value.shape}, the scene's solver expects {view.shape}")
    view[...] = value


def view_camera(output, dim, lower, upper, default_axes):
    """A preview camera on the output's ``view`` axes (or the adapter's default) over the
    bounding box (lower, upper), with a 5% margin, ``output.width`` pixels wide."""
    axes = tuple(output["view"] or default_axes)
    lo = np.array([lower[a] for a in axes], float)
    hi = np.array([upper[a] for a in axes], float)
    pad = 0.05 * (hi - lo).max()
    return preview.Camera(axes, lo - pad, hi + pad, output["width"])
