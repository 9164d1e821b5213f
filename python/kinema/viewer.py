"""A live viewer for simulations and finished runs, built on Polyscope (``pip install kinema[viewer]``).

    v = km.viewer.Viewer("dam_break", quick=True)   # a scene name, file or km.Scene
    v.show()                                         # a window; returns when it is closed

    km.viewer.Viewer.for_run("out/dam").show()       # scrub a finished run's VTU/PLY/VTI files

What it draws, from what the scene's solver reports each frame (its VTU/PLY/VTI data):
particles as spheres coloured by a quantity (2D and 3D), triangle surfaces (cloth, soft bodies,
fluid surfaces) with their vertex quantities, 2D grid fields as colour-mapped images with the
velocity as arrows on a coarse lattice of cells (about ARROWS_ACROSS across), and 3D
grids as a volume with a slice plane. The camera orbits (left drag), pans (right drag) and
zooms (wheel). A panel holds Run/Pause, Step, Reset, the quantity picker and the simulated
time, frame and step rate. Keys: space pauses or runs, N (or the right arrow) takes one frame,
R resets.

The same calls work without the window, for scripts and tests: :meth:`Viewer.step`,
:meth:`Viewer.pause`, :meth:`Viewer.reset`, :meth:`Viewer.tick` (one drawn frame) and
:meth:`Viewer.screenshot`. Polyscope needs an OpenGL display: where none can be opened (no
``DISPLAY`` on Linux) :class:`ViewerUnavailable` says so, and how to get one (``xvfb-run``).
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

import numpy as np

from kinema.errors import KinemaError

__all__ = ["Viewer", "ViewerUnavailable", "display_problem", "SceneSource", "RunSource", "CallbackSource"]

#: Background of the 3D view (dark grey, as the preview's): particle colours stand out.
BACKGROUND = (0.1, 0.1, 0.12)
#: Solid colours of the structures when no quantity is picked (fluid blue, solids grey).
FLUID_COLOR = (0.2, 0.45, 0.9)
SOLID_COLOR = (0.6, 0.6, 0.6)
NONE = "(none)"
#: Arrows across a 2D grid's longer side for its vector field; their colour.
ARROWS_ACROSS = 32
ARROW_COLOR = (0.95, 0.95, 0.95)
#: Particle counts above which particles are not Polyscope point clouds but spheres splatted on
#: the CPU by km.render.splat_spheres (depth, normal and quantity per pixel) and composited into
#: Polyscope's view by depth (its render-image quantities), with points="auto". Polyscope expands
#: every point in a geometry shader, which Mesa's software OpenGL (llvmpipe, what a machine
#: without a GPU has) runs on the CPU: about 100 ms per 1e5 points, against milliseconds for the
#: splat (bench/render/viewer_bench.py). On a GPU, points="polyscope" is the faster choice.
SPLAT_ABOVE = 20_000
SPLAT_NAME = "particles (splatted)"


class ViewerUnavailable(KinemaError):
    """The viewer cannot run here: Polyscope is missing or no OpenGL display can be opened."""


def display_problem():
    """Why no window can be opened here (a sentence), or None when a display is available."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return ("no display: DISPLAY is not set. Run under a virtual one, e.g. "
                "`xvfb-run -a kinema ...` (Debian: apt-get install xvfb libgl1-mesa-dri), "
                "or use `kinema run` without --view for PNG frames and a video")
    return None


def _polyscope():
    try:
        import polyscope
        import polyscope.imgui
    except ImportError:
        raise ViewerUnavailable("the viewer needs Polyscope: pip install 'kinema[viewer]' "
                                "(scripts/setup.sh viewer installs it)") from None
    return polyscope


_initialised = False


def _init(ps, width, height, title):
    """Polyscope's one window for the process (Polyscope is a singleton: one viewer at a time)."""
    global _initialised
    problem = display_problem()
    if problem:
        raise ViewerUnavailable(problem)
    if not _initialised:
        ps.set_program_name(title)
        ps.set_window_size(int(width), int(height))
        ps.set_enable_vsync(False)
        ps.set_max_fps(-1)
        ps.set_automatically_compute_scene_extents(False)
        ps.set_build_default_gui_panels(False)
        ps.set_use_prefs_file(False)  # no .polyscope.ini in the working folder
        try:
            ps.init("openGL3_glfw")
        except Exception as exc:  # GLFW/GL errors surface as RuntimeError with Polyscope's text
            raise ViewerUnavailable(f"cannot open an OpenGL window ({exc}); under Linux without a "
                                    "screen run through `xvfb-run -a` with Mesa (libgl1-mesa-dri)") from None
        _initialised = True
    ps.remove_all_structures()
    ps.remove_all_slice_planes() if hasattr(ps, "remove_all_slice_planes") else None
    ps.set_background_color(BACKGROUND)
    ps.set_ground_plane_mode("shadow_only")
    ps.set_up_dir("y_up")
    ps.set_front_dir("z_front")


# ------------------------------------------------------------------ sources


class SceneSource:
    """A scene simulated frame by frame (frame k at t = k / fps)."""

    def __init__(self, scene):
        self.scene = scene
        self.name = scene.name
        self.reset()

    def reset(self):
        self.sim = self.scene.build()
        self.frame = 0

    @property
    def time(self):
        return self.sim.time

    @property
    def frame_count(self):
        return None  # open-ended

    def advance(self):
        """One frame; returns the solver steps taken."""
        self.frame += 1
        return self.sim.advance_to(self.frame / self.scene.fps)

    def seek(self, frame):
        raise ValueError("frame: a live simulation cannot seek; use reset() and step()")

    def items(self):
        return self.sim.data()

    def domain(self):
        """(lower, upper) of the box the scene lives in, or None."""
        lo, hi = getattr(self.sim, "lower", None), getattr(self.sim, "upper", None)
        return (np.asarray(lo, float), np.asarray(hi, float)) if lo is not None and hi is not None else None


class RunSource:
    """A finished run's data files (``kinema run`` with vtu, ply or vti on): the frames that
    hold files, scrubbed forwards (wrapping round), backwards with :meth:`seek`."""

    PATTERN = re.compile(r"^(?P<name>.+)_(?P<frame>\d{5})\.(?P<ext>vtu|ply|vti)$")

    def __init__(self, out):
        self.out = Path(out)
        if not self.out.is_dir():
            raise FileNotFoundError(f"out: no such folder {self.out}")
        self.files = {}  # frame -> {name: path}
        static = {}
        for path in sorted(self.out.glob("*/*_?????.*")):
            m = self.PATTERN.match(path.name)
            if not m or path.parent.name != m["name"]:
                continue
            # VTU carries the point data; PLY only where there is no VTU of that frame.
            slot = self.files.setdefault(int(m["frame"]), {})
            if m["name"] not in slot or m["ext"] == "vtu":
                slot[m["name"]] = path
        if not self.files:
            raise FileNotFoundError(f"out: {self.out} holds no VTU, PLY or VTI frame files (run the scene "
                                    "with output.vtu, output.ply or output.vti on)")
        # Items written once (the static obstacles at frame 0) stay on screen in later frames.
        for frame in sorted(self.files):
            for name, path in self.files[frame].items():
                static.setdefault(name, path)
        self.static = {name: p for name, p in static.items()
                       if sum(name in f for f in self.files.values()) == 1 and len(self.files) > 1}
        self.frames = sorted(self.files)
        self.name = self.out.name
        fps = 30.0
        self._fps = fps
        self.index = 0

    @property
    def frame(self):
        return self.frames[self.index]

    @property
    def frame_count(self):
        return len(self.frames)

    @property
    def time(self):
        return self._times().get(self.frame, self.frame / self._fps)

    def _times(self):
        if not hasattr(self, "_time_table"):
            self._time_table = {}
            path = self.out / "diagnostics.csv"
            if path.exists():
                import csv

                with open(path, newline="") as fh:
                    for row in csv.DictReader(fh):
                        self._time_table[int(row["frame"])] = float(row["time"])
        return self._time_table

    def reset(self):
        self.index = 0

    def advance(self):
        self.index = (self.index + 1) % len(self.frames)
        return 1

    def seek(self, frame):
        """Shows the file frame nearest to ``frame`` (a frame number of the run)."""
        self.index = int(np.argmin(np.abs(np.asarray(self.frames) - int(frame))))

    def items(self):
        paths = dict(self.static)
        paths.update(self.files[self.frame])
        return [read_item(name, p) for name, p in sorted(paths.items())]

    def domain(self):
        return None


def read_item(name, path):
    """A data file of a run as the PointData / GridData the adapters report."""
    from kinema.scenes.adapters.base import GridData, PointData

    path = Path(path)
    if path.suffix == ".vti":
        from kinema.io import read_vtk

        data = read_vtk(path)
        fields, spacing = data["fields"], data["spacing"]
        if all(f.shape[2] == 1 for f in fields.values()):
            fields = {k: v[:, :, 0] for k, v in fields.items()}
        return GridData(name, fields, spacing[0])
    import meshio

    mesh = meshio.read(path)
    tris = None
    for block in mesh.cells:
        if block.type == "triangle":
            tris = np.asarray(block.data, np.int64)
        elif block.type == "tetra" and tris is None:
            from kinema.scenes.preview import boundary_faces

            tris = boundary_faces(block.data)
    data = {k: np.asarray(v, float) for k, v in mesh.point_data.items()}
    return PointData(name, np.asarray(mesh.points, float), point_data=data, surface=tris)


class CallbackSource:
    """Any simulation: ``step()`` advances it one frame, ``items()`` lists what to draw (a dict
    name -> (n, d) points, or name -> (points, {quantity: (n,) or (n, d) values}), or PointData /
    GridData items), ``reset()`` (optional) starts it again, ``time()`` (optional) its time."""

    def __init__(self, step, items, reset=None, time=None, name="simulation"):
        self._step, self._items, self._reset, self._time = step, items, reset, time
        self.name = name
        self.frame = 0

    @property
    def time(self):
        return float(self._time()) if self._time else float(self.frame)

    @property
    def frame_count(self):
        return None

    def reset(self):
        if self._reset is None:
            raise ValueError("reset: this viewer was built without a reset callback")
        self._reset()
        self.frame = 0

    def advance(self):
        self.frame += 1
        taken = self._step()
        return int(taken) if isinstance(taken, (int, np.integer)) else 1

    def seek(self, frame):
        raise ValueError("frame: a live simulation cannot seek")

    def items(self):
        from kinema.scenes.adapters.base import PointData

        got = self._items()
        if isinstance(got, dict):
            out = []
            for name, value in got.items():
                points, data = (value if isinstance(value, tuple) else (value, {}))
                out.append(PointData(name, np.asarray(points, float), point_data=dict(data)))
            return out
        return list(got)

    def domain(self):
        return None


# ------------------------------------------------------------------ the viewer


def _source(source, quick, overrides):
    if isinstance(source, (SceneSource, RunSource, CallbackSource)):
        return source
    from kinema.scenes.scene import Scene

    if isinstance(source, Scene):
        return SceneSource(source)
    if isinstance(source, (str, os.PathLike)):
        p = Path(source)
        if p.is_dir():
            return RunSource(p)
        from kinema.scenes import resolve

        return SceneSource(Scene.load(resolve(str(source)), overrides=overrides, quick=quick))
    raise ValueError(f"source: expected a km.Scene, a scene name or file, a run folder or a "
                     f"CallbackSource, got {source!r}")


def _scalars(values):
    """(n,) scalars of a quantity: itself, or the norm of vectors."""
    v = np.asarray(values, float)
    return v if v.ndim == 1 else np.linalg.norm(v.reshape(len(v), -1), axis=1)


def _pad3(points):
    p = np.asarray(points, float)
    return p if p.shape[1] == 3 else np.hstack([p, np.zeros((len(p), 3 - p.shape[1]))])


class Viewer:
    """A window showing a simulation while it steps, or a finished run.

    source: a km.Scene, an example name or scene file (``quick`` and ``overrides`` as in
    km.Scene.load), a run folder (see :meth:`for_run`) or a :class:`CallbackSource`.
    quantity: the quantity to colour by at start (default: the first one, e.g. velocity).
    point_radius: sphere radius of particles [m] (default: from the scene's spacing, or 0.4%
    of the scene's size). paused: start paused. width, height: window size [pixels].
    points: how particles are drawn: "polyscope" (Polyscope's sphere impostors, best on a GPU),
    "splat" (spheres splatted on the CPU and composited by depth, best on a software renderer)
    or "auto" (splat above SPLAT_ABOVE particles). splat_scale: resolution of the splat relative
    to the window, in (0, 1]: the default 0.5 splats a quarter of the pixels (1e5 particles in a
    1024 x 768 window on Mesa's software OpenGL: 22 fps, against 12 fps at 1.0).
    """

    def __init__(self, source, *, quantity=None, point_radius=None, paused=False, width=1024, height=768,
                 quick=False, overrides=(), cmap="viridis", points="auto", splat_scale=0.5):
        if points not in ("auto", "polyscope", "splat"):
            raise ValueError(f"points: expected 'auto', 'polyscope' or 'splat', got {points!r}")
        if isinstance(splat_scale, bool) or not isinstance(splat_scale, (int, float)) or \
                not 0 < splat_scale <= 1:
            raise ValueError(f"splat_scale: expected a number in (0, 1], got {splat_scale!r}")
        self.points = points
        self.splat_scale = float(splat_scale)
        self._splats = {}  # name -> (points, radius, point data, solid) of splatted particles
        self._splat_view = None  # camera and size the splats were made for
        self._splat_buffers = None  # ((w, h), Polyscope buffers) of the splat image
        self.ps = _polyscope()
        self.source = _source(source, quick, overrides)
        _init(self.ps, width, height, f"kinema: {self.source.name}")
        self.paused = bool(paused)
        self.cmap = cmap
        self.point_radius = point_radius
        self.steps_per_second = 0.0  # solver steps per wall second, over the last frames
        self.frames_per_second = 0.0  # drawn frames per wall second
        self._rates = []
        self._structures = {}
        self._last_tick = None
        self._quantity = quantity
        self._radius = None
        self._draw()
        self._home()
        self.ps.set_user_callback(self._gui)

    @classmethod
    def for_run(cls, out, **kwargs):
        """The viewer of a finished run's folder (its VTU/PLY/VTI frame files), paused."""
        kwargs.setdefault("paused", True)
        return cls(RunSource(out), **kwargs)

    # ---------------------------------------------------------- state

    @property
    def time(self) -> float:
        """Simulated time of the frame shown [s]."""
        return self.source.time

    @property
    def frame(self) -> int:
        return self.source.frame

    @property
    def quantities(self) -> list:
        """The names the quantity picker offers: (none) and every per-point or grid quantity."""
        names = []
        for item in self._items:
            for key in (item.point_data if hasattr(item, "point_data") else item.fields):
                if key not in names:
                    names.append(key)
        return [NONE] + names

    @property
    def quantity(self) -> str:
        return self._quantity

    @quantity.setter
    def quantity(self, name):
        if name not in self.quantities:
            raise ValueError(f"quantity: expected one of {self.quantities}, got {name!r}")
        self._quantity = name
        self._update()

    def pause(self):
        self.paused = True

    def resume(self):
        self.paused = False

    def toggle(self):
        self.paused = not self.paused

    def step(self, frames=1):
        """Advances ``frames`` frames (also while paused) and redraws."""
        for _ in range(int(frames)):
            t0 = time.perf_counter()
            taken = self.source.advance()
            dt = time.perf_counter() - t0
            self._rates = (self._rates + [(taken, dt)])[-10:]
            wall = sum(d for _, d in self._rates)
            self.steps_per_second = sum(s for s, _ in self._rates) / wall if wall > 0 else 0.0
        self._draw()

    def seek(self, frame):
        """Shows a frame of a finished run (the nearest one with files)."""
        self.source.seek(frame)
        self._draw()

    def reset(self):
        """Back to the start: a scene is rebuilt, a run shows its first frame."""
        self.source.reset()
        self.ps.remove_all_structures()
        self._remove_splats()
        self._structures = {}
        self._rates = []
        self.steps_per_second = 0.0
        self._draw()

    def handle_key(self, key):
        """What the keys do: "space" pause/run, "n" or "right" one frame, "r" reset."""
        key = key.lower()
        if key == "space":
            self.toggle()
        elif key in ("n", "right"):
            self.step()
        elif key == "r":
            self.reset()
        else:
            raise ValueError(f"key: expected 'space', 'n', 'right' or 'r', got {key!r}")

    # ---------------------------------------------------------- drawing

    def tick(self, frames=1):
        """Draws ``frames`` window frames, advancing the simulation before each unless paused."""
        for _ in range(int(frames)):
            if not self.paused:
                self.step()
            now = time.perf_counter()
            if self._last_tick is not None and now > self._last_tick:
                self.frames_per_second = 0.8 * self.frames_per_second + 0.2 / (now - self._last_tick) \
                    if self.frames_per_second else 1.0 / (now - self._last_tick)
            self._last_tick = now
            self._refresh_splats()
            self.ps.frame_tick()

    def show(self):
        """Opens the window and runs until it is closed (Esc or the window's close button)."""
        while not self.ps.window_requests_close():
            self.tick()
        self.ps.unshow() if hasattr(self.ps, "unshow") else None

    def screenshot(self, path=None):
        """The view (without the panel) as an (H, W, 3) uint8 array; also a PNG at ``path``."""
        self._refresh_splats()
        self.ps.frame_tick()
        rgba = np.asarray(self.ps.screenshot_to_buffer(transparent_bg=False, include_UI=False))
        rgb = np.ascontiguousarray(rgba[..., :3])
        if path is not None:
            from kinema.scenes.output import write_png

            write_png(Path(path), rgb)
        return rgb

    def camera(self):
        """(view matrix 4x4, vertical field of view [deg], aspect) of the current camera."""
        p = self.ps.get_view_camera_parameters()
        return np.asarray(p.get_view_mat()), p.get_fov_vertical_deg(), p.get_aspect()

    def project(self, points):
        """Pixel (column, row) of world points in the screenshot (row 0 at the top)."""
        view, fov, aspect = self.camera()
        w, h = self.ps.get_window_size() if hasattr(self.ps, "get_window_size") else self._size
        q = np.c_[_pad3(points), np.ones(len(points))] @ view.T
        f = 1.0 / np.tan(np.radians(fov) / 2)
        ndc_x = f / aspect * q[:, 0] / -q[:, 2]
        ndc_y = f * q[:, 1] / -q[:, 2]
        return (ndc_x + 1) * 0.5 * w, (1 - ndc_y) * 0.5 * h

    def close(self):
        """Removes what this viewer drew (Polyscope's window stays for the next viewer)."""
        self.ps.set_user_callback(None)
        self.ps.remove_all_structures()
        self._remove_splats()
        self._structures = {}

    def _draw(self):
        self._items = self.source.items()
        if self._quantity is None or self._quantity not in self.quantities:
            qs = self.quantities
            self._quantity = next((q for q in qs if q in ("velocity", "density")), qs[1] if len(qs) > 1 else NONE)
        self._update()

    def _lengths(self):
        """A length scale of the scene: its box diagonal, from the domain or the data."""
        dom = self.source.domain()
        if dom is not None:
            return float(np.linalg.norm(dom[1] - dom[0]))
        pts = [np.asarray(i.points) for i in self._items if hasattr(i, "points") and len(i.points)]
        if not pts:
            return 1.0
        p = np.concatenate([_pad3(x) for x in pts])
        return float(np.linalg.norm(p.max(0) - p.min(0))) or 1.0

    def _update(self):
        # Items a solver reports once (static obstacles at frame 0) stay drawn until a reset.
        ps = self.ps
        for item in self._items:
            if hasattr(item, "fields"):
                self._draw_grid(item)
            elif item.surface is not None and len(item.surface):
                self._draw_surface(item)
            else:
                self._draw_points(item)
        if "domain" not in self._structures and self.source.domain() is not None:
            lo, hi = self.source.domain()
            corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
            if len(lo) == 2:
                lo, hi = np.r_[lo, 0.0], np.r_[hi, 0.0]
            nodes = lo + corners * (hi - lo)
            edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
            net = ps.register_curve_network("domain", nodes, np.array(edges), radius=0.002, color=SOLID_COLOR)
            self._structures["domain"] = ("curve_network", net)

    def _colour(self, structure, item_data, defined_on=None):
        q = self._quantity
        for key, values in item_data.items():
            kwargs = {"defined_on": defined_on} if defined_on else {}
            structure.add_scalar_quantity(key, _scalars(values), enabled=(key == q), cmap=self.cmap, **kwargs)

    def _point_radius(self, n):
        if self.point_radius is not None:
            return float(self.point_radius)
        sim = getattr(self.source, "sim", None)
        spacing = getattr(sim, "spacing", None)
        return 0.5 * spacing if spacing else 0.004 * self._lengths()

    def _draw_points(self, item):
        ps = self.ps
        pts = _pad3(item.points)
        solid = not item.point_data
        if self.points == "splat" or (self.points == "auto" and len(pts) > SPLAT_ABOVE):
            radius = self._splats[item.name][1] if item.name in self._splats else self._point_radius(len(pts))
            self._splats[item.name] = (pts, radius, item.point_data, solid)
            self._splat_view = None  # redrawn before the next frame
            # Polyscope's ground plane writes depth where its shadow is drawn, which would cut the
            # composited spheres at the floor: no ground plane with splats.
            ps.set_ground_plane_mode("none")
            return
        entry = self._structures.get(item.name)
        if entry and entry[0] == "point_cloud" and entry[1].n_points() == len(pts):
            pc = entry[1]
            pc.update_point_positions(pts)
        else:
            pc = ps.register_point_cloud(item.name, pts, color=SOLID_COLOR if solid else FLUID_COLOR)
            pc.set_radius(self._point_radius(len(pts)), relative=False)
            self._structures[item.name] = ("point_cloud", pc)
        self._colour(pc, item.point_data)
        v = item.point_data.get("velocity")
        if v is not None and np.ndim(v) == 2 and len(pts) <= 20_000:
            pc.add_vector_quantity("velocity vectors", _pad3(v), enabled=False)

    def _refresh_splats(self):
        """Splats the particles again when they, the quantity or the camera changed since the
        last splat. All splatted items go into one image (one depth buffer: they hide each other
        correctly), coloured per particle by the quantity's colormap or their solid colour."""
        if not self._splats:
            return
        from kinema.render import Camera, splat_spheres

        ps = self.ps
        params = ps.get_view_camera_parameters()
        width, height = ps.get_buffer_size()
        w, h = max(1, round(width * self.splat_scale)), max(1, round(height * self.splat_scale))
        view = (np.asarray(params.get_view_mat()).tobytes(), params.get_fov_vertical_deg(), w, h, self._quantity)
        if view == self._splat_view:
            return
        eye, look, up = (np.asarray(v, float) for v in (params.get_position(), params.get_look_dir(),
                                                          params.get_up_dir()))
        camera = Camera(tuple(eye), tuple(eye + look), tuple(up), params.get_fov_vertical_deg(), width=w, height=h)
        points, radii, colours = [], [], []
        for pts, radius, data, solid in self._splats.values():
            points.append(pts)
            radii.append(np.full(len(pts), radius))
            colours.append(self._particle_colours(data, solid, len(pts)))
        depth, normals, ids, _ = splat_spheres(camera, np.concatenate(points), np.concatenate(radii))
        table = np.concatenate(colours + [np.zeros((1, 3), np.float32)])  # ids of -1: the last row
        flat_ids = ids.reshape(-1)
        # Polyscope's (n, 3) buffers are column-major: fill each colour channel as one column.
        image = np.empty((flat_ids.size, 3), np.float32, order="F")
        for c in range(3):
            np.take(table[:, c], flat_ids, out=image[:, c])
        normals = np.asfortranarray(normals.reshape(-1, 3))
        updated = False
        if self._splat_buffers is not None and self._splat_buffers[0] == (w, h):
            # Same size: new data into the quantity's GPU buffers (re-adding it costs ~15 ms more).
            try:
                for buffer, data in zip(self._splat_buffers[1], (depth.reshape(-1), normals, image)):
                    buffer.update_data(data)
                updated = True
            except ValueError:  # the quantity went with Polyscope's structures: add it again
                pass
        if not updated:
            ps.add_color_render_image_quantity(SPLAT_NAME, depth, normals.reshape(h, w, 3), image.reshape(h, w, 3),
                                               enabled=True, allow_fullscreen_compositing=True)
            self._splat_buffers = ((w, h), [ps.get_quantity_buffer(SPLAT_NAME, b)
                                            for b in ("depths", "normals", "colors")])
        self._splat_view = view

    def _particle_colours(self, data, solid, n):
        """(n, 3) float32 colours of splatted particles: the picked quantity through the colormap
        (scaled to its range in this frame, as Polyscope's point clouds do), else a solid colour."""
        q = self._quantity
        if q not in data:
            return np.tile(np.asarray(SOLID_COLOR if solid else FLUID_COLOR, np.float32), (n, 1))
        import matplotlib

        values = _scalars(data[q])
        lo, hi = float(values.min()), float(values.max())
        t = (values - lo) / (hi - lo) if hi > lo else np.full(n, 0.5)
        return matplotlib.colormaps[self.cmap](t)[:, :3].astype(np.float32)

    def _remove_splats(self):
        if self._splats:
            from polyscope.global_floating_quantity_structure import FloatingQuantityStructure

            FloatingQuantityStructure().remove_quantity(SPLAT_NAME, error_if_absent=False)
        self._splats = {}
        self._splat_view = None
        self._splat_buffers = None

    def _draw_surface(self, item):
        ps = self.ps
        pts = _pad3(item.points)
        entry = self._structures.get(item.name)
        if entry and entry[0] == "surface_mesh" and entry[1].n_vertices() == len(pts) \
                and entry[1].n_faces() == len(item.surface):
            mesh = entry[1]
            mesh.update_vertex_positions(pts)
        else:
            liquid = item.name == "surface"  # a liquid's free surface over its particles: hidden at first
            mesh = ps.register_surface_mesh(item.name, pts, np.asarray(item.surface),
                                            color=(0.3, 0.55, 0.85) if liquid else (0.85, 0.4, 0.3),
                                            edge_width=0.0 if liquid else 1.0, smooth_shade=True, enabled=not liquid)
            self._structures[item.name] = ("surface_mesh", mesh)
        self._colour(mesh, item.point_data, "vertices")

    def _draw_grid(self, item):
        ps = self.ps
        first = next(iter(item.fields.values()))
        h = item.h
        if not _flat(item):
            shape = first.shape[:3]
            entry = self._structures.get(item.name)
            if not entry:
                grid = ps.register_volume_grid(item.name, tuple(s + 1 for s in shape), (0.0, 0.0, 0.0),
                                               tuple(s * h for s in shape))
                self._structures[item.name] = ("volume_grid", grid)
                plane = ps.add_scene_slice_plane()
                plane.set_pose((0.0, 0.0, shape[2] * h / 2), (0.0, 0.0, -1.0))
            grid = self._structures[item.name][1]
            for key, values in item.fields.items():
                v = values if values.ndim == 3 else np.linalg.norm(values, axis=-1)
                grid.add_scalar_quantity(key, np.ascontiguousarray(v), defined_on="cells",
                                         enabled=(key == self._quantity), cmap=self.cmap)
            return
        nx, ny = first.shape[:2]
        entry = self._structures.get(item.name)
        if not entry:
            gx, gy = np.meshgrid(np.arange(nx + 1) * h, np.arange(ny + 1) * h, indexing="ij")
            verts = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
            idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
            quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
            mesh = ps.register_surface_mesh(item.name, verts, quads, color=SOLID_COLOR)
            mesh.set_material("flat")
            self._structures[item.name] = ("surface_mesh", mesh)
        mesh = self._structures[item.name][1]
        for key, values in item.fields.items():
            v = values if values.ndim == 2 else np.linalg.norm(values, axis=-1)
            mesh.add_scalar_quantity(key, v.reshape(-1), defined_on="faces", enabled=(key == self._quantity),
                                     cmap=self.cmap)
        self._draw_arrows(item, nx, ny, h)

    def _draw_arrows(self, item, nx, ny, h):
        """Arrows of a 2D grid's vector field (the velocity) at every `stride`-th cell centre,
        about ARROWS_ACROSS of them across the grid: one arrow per cell would be a carpet."""
        key = next((k for k, f in item.fields.items() if f.ndim == 3 and f.shape[-1] == 2), None)
        if key is None:
            return
        field = item.fields[key]
        stride = max(1, max(nx, ny) // ARROWS_ACROSS)
        sub = field[stride // 2::stride, stride // 2::stride]
        ci, cj = np.meshgrid(np.arange(stride // 2, nx, stride), np.arange(stride // 2, ny, stride),
                             indexing="ij")
        centres = np.c_[(ci.ravel() + 0.5) * h, (cj.ravel() + 0.5) * h, np.full(ci.size, 1e-3 * h)]
        name = f"{item.name} {key} arrows"
        entry = self._structures.get(name)
        if entry and entry[1].n_points() == len(centres):
            cloud = entry[1]
        else:
            cloud = self.ps.register_point_cloud(name, centres, radius=1e-6, color=SOLID_COLOR)
            self._structures[name] = ("point_cloud", cloud)
        vectors = _pad3(sub.reshape(-1, 2))
        # Drawn at their own length ("ambient"), scaled so that the longest spans the stride.
        top = float(np.linalg.norm(vectors, axis=1).max()) if vectors.size else 0.0
        scaled = vectors * (stride * h / top) if top > 0 else vectors
        cloud.add_vector_quantity(key, scaled, enabled=True, color=ARROW_COLOR, vectortype="ambient",
                                  radius=0.1 * stride * h / self._lengths())

    def _home(self):
        """Looks at the scene from the front, a little from above and the right; 2D scenes
        straight on (planar navigation)."""
        dom = self.source.domain()
        pts = [_pad3(i.points) for i in self._items if hasattr(i, "points") and len(i.points)]
        grids = [i for i in self._items if hasattr(i, "fields")]
        if dom is not None:
            lo, hi = _pad3(dom[0][None])[0], _pad3(dom[1][None])[0]
        elif pts:
            p = np.concatenate(pts)
            lo, hi = p.min(0), p.max(0)
        elif grids:
            g = grids[0]
            f = next(v for v in g.fields.values() if v.ndim == (2 if _flat(g) else 3))
            lo, hi = np.zeros(3), _pad3(np.array(f.shape, float)[None])[0] * g.h
        else:
            lo, hi = np.zeros(3), np.ones(3)
        self._size = None
        centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) or 1.0
        self.ps.set_length_scale(extent) if hasattr(self.ps, "set_length_scale") else None
        self.ps.set_bounding_box(lo, hi) if hasattr(self.ps, "set_bounding_box") else None
        if hi[2] - lo[2] <= 1e-12 * extent:  # planar
            self.ps.set_navigation_style("planar")
            eye = centre + np.array([0.0, 0.0, 1.25 * max(hi[0] - lo[0], hi[1] - lo[1])])
        else:
            self.ps.set_navigation_style("turntable")
            eye = centre + 1.1 * extent * np.array([0.35, 0.35, 0.85])
        self.ps.look_at(tuple(eye), tuple(centre))

    # ---------------------------------------------------------- panel

    def _gui(self):
        import polyscope.imgui as psim

        psim.SetNextWindowPos((10, 10))
        psim.Begin("kinema", True)
        if psim.Button("Run" if self.paused else "Pause"):
            self.toggle()
        psim.SameLine()
        if psim.Button("Step"):
            self.step()
        psim.SameLine()
        if psim.Button("Reset"):
            self.reset()
        qs = self.quantities
        changed, index = psim.Combo("quantity", qs.index(self._quantity) if self._quantity in qs else 0, qs)
        if changed:
            self.quantity = qs[index]
        count = self.source.frame_count
        if count:
            changed, k = psim.SliderInt("frame", self.source.index, 0, count - 1)
            if changed:
                self.source.index = k
                self._draw()
        psim.Text(f"t = {self.time:.4g} s   frame {self.frame}")
        psim.Text(f"{self.steps_per_second:.1f} steps/s   {self.frames_per_second:.1f} fps")
        psim.Text("space: run/pause   N: step   R: reset")
        for name, (_, structure) in self._structures.items():
            changed, on = psim.Checkbox(name, structure.is_enabled())
            if changed:
                structure.set_enabled(on)
        psim.End()
        io = psim.GetIO()
        if not io.WantCaptureKeyboard:
            for key, name in ((psim.ImGuiKey_Space, "space"), (psim.ImGuiKey_N, "n"),
                              (psim.ImGuiKey_RightArrow, "right"), (psim.ImGuiKey_R, "r")):
                if psim.IsKeyPressed(key, False):
                    self.handle_key(name)


def _flat(grid):
    """A 2D grid: a scalar field is [i, j] (vectors [i, j, 2]; 3D grids have [i, j, k] scalars)."""
    return any(v.ndim == 2 for v in grid.fields.values())


def view(source, **kwargs):
    """Opens a :class:`Viewer` on ``source`` and runs it until the window is closed."""
    v = Viewer(source, **kwargs)
    try:
        v.show()
    finally:
        v.close()
    return v


def cli_view(source):
    """``kinema run SCENE --view`` and ``kinema view OUT_DIR``: the window, or one clear line
    on stderr (exit status 2) where it cannot open."""
    from kinema.scenes import SceneError

    try:
        view(source)
    except (ViewerUnavailable, FileNotFoundError, SceneError) as exc:
        print(f"kinema: {exc}", file=sys.stderr)
        return 2
    return 0
