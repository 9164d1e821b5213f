"""Scene files (kinema.scenes): validation messages, every example scene end to end with real
files, bit-for-bit resume for every solver, atomic writes and interruption, and a Dask sweep."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kinema as km
from kinema.scenes import SceneError, examples, output
from kinema.scenes.adapters import ADAPTERS

EXAMPLES = examples()
ALL_DATA = [("output.vtu", True), ("output.ply", True), ("output.vti", True), ("output.every", 1)]

GRID_SCENE = """
[scene]
name = "t"
duration = 0.1
threads = 1
[solver]
type = "grid"
resolution = [16, 16]
[[objects]]
type = "obstacle"
region = { shape = "sphere", center = [0.5, 0.5], radius = 0.1 }
[[objects]]
type = "block"
region = { shape = "box", lower = [0.1, 0.1], upper = [0.3, 0.3] }
velocity = [1.0, 0.0]
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------- validation

@pytest.mark.parametrize("edit, key, expected", [
    (("[[objects]]\ntype = \"obstacle\"", "[[objects]]\ntype = \"obstacle\"\nsize = 3"), "objects[0].size", "unknown key"),
    (("resolution = [16, 16]", "resolution = \"big\""), "solver.resolution", "expected an array of 2 or 3 items, each an integer >= 1"),
    (("resolution = [16, 16]", "resolution = [16, 1.5]"), "solver.resolution[1]", "expected an integer >= 1"),
    (("duration = 0.1", ""), "scene.duration", "missing required key"),
    (("type = \"grid\"", "type = \"lbm\""), "solver.type", "expected one of \"grid\", \"sph\""),
    (("radius = 0.1", "radius = -0.1"), "objects[0].region.radius", "expected a number > 0"),
    (("center = [0.5, 0.5]", "center = [0.5, 0.5, 0.5]"), "objects[0].region.center", "expected 2 components"),
    (("shape = \"sphere\"", "shape = \"cone\""), "objects[0].region.shape", "expected one of \"box\", \"sphere\""),
    (("type = \"block\"", "type = \"fluid\""), "objects[1].type", "expected one of \"obstacle\""),
    (("velocity = [1.0, 0.0]", "velocity = [true, 0.0]"), "objects[1].velocity[0]", "expected a number"),
    (("velocity = [1.0, 0.0]", "velocity = [nan, 0.0]"), "objects[1].velocity[0]",
     "expected a finite number, got a number nan"),
    (("radius = 0.1", "radius = inf"), "objects[0].region.radius", "expected a finite number > 0, got a number inf"),
    (("[scene]", "[scenery]\nx = 1\n[scene]"), "scenery", "unknown table"),
    # [output] rendering keys; a 2D grid scene has only the flat view
    (("[solver]", "[output]\nrender = \"raytrace\"\n[solver]"), "output.render",
     'expected one of "flat", "preview", "pathtrace"'),
    (("[solver]", "[output]\nrender = \"pathtrace\"\n[solver]"), "output.render", 'has only "flat"'),
    (("[solver]", "[output]\nspp = 0\n[solver]"), "output.spp", "expected an integer >= 1"),
    (("[solver]", "[output]\ncamera = { vfov = \"wide\" }\n[solver]"), "output.camera.vfov", "expected a number > 0"),
    (("[solver]", "[output]\ncamera = { look_from = [1, 2] }\n[solver]"), "output.camera.look_from",
     "expected an array of 3 items"),
    (("[solver]", "[output]\ncamera = { fov = 30 }\n[solver]"), "output.camera.fov", "unknown key"),
    (("[solver]", "[output]\ncamera = 3\n[solver]"), "output.camera", "expected a table"),
])
def test_validation_names_file_key_path_and_expectation(tmp_path, edit, key, expected):
    old, new = edit
    assert old in GRID_SCENE
    path = write(tmp_path, GRID_SCENE.replace(old, new, 1))
    with pytest.raises(SceneError) as err:
        km.Scene.load(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: {key}: "), msg
    assert expected in msg, msg
    assert isinstance(err.value, ValueError)


def test_valid_scene_fills_defaults_and_builds_only_what_it_names(tmp_path):
    scene = km.Scene.load(write(tmp_path, GRID_SCENE))
    assert scene.solver == "grid" and scene.dim == 2
    assert scene.config["solver"]["advection"] == "maccormack"
    assert scene.config["output"]["png"] is True
    sim = scene.build()
    # Fields the scene does not name are not allocated.
    with pytest.raises(AttributeError, match="density"):
        sim.fluid.density
    # The block's velocity landed on the faces of its cells, the obstacle in the solid mask.
    assert sim.fluid.u.max() == 1.0 and sim.fluid.solid.sum() > 0


def test_only_the_named_adapter_is_imported(tmp_path):
    path = write(tmp_path, GRID_SCENE)
    code = ("import sys, kinema as km; km.Scene.load(sys.argv[1]).build(); "
            "print(sorted(m for m in sys.modules if m.startswith('kinema.scenes.adapters.')))")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(["kinema.scenes.adapters.base", "kinema.scenes.adapters.grid"]), out.stdout


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(SceneError, match="not valid TOML"):
        km.Scene.load(write(tmp_path, "[scene\nname = 1"))
    with pytest.raises(SceneError, match="no such scene file"):
        km.Scene.load(tmp_path / "missing.toml")


def test_overrides_and_quick_profile(tmp_path):
    path = write(tmp_path, GRID_SCENE + '\n[quick]\nsolver.resolution = [8, 8]\n"objects[1].velocity" = [2.0, 0.0]\n')
    assert km.Scene.load(path).config["solver"]["resolution"] == [16, 16]
    quick = km.Scene.load(path, quick=True)
    assert quick.config["solver"]["resolution"] == [8, 8]
    assert quick.config["objects"][1]["velocity"] == [2.0, 0.0]
    s = km.Scene.load(path, overrides=[("objects[0].region.radius", 0.2), ("output.vti", True)])
    assert s.config["objects"][0]["region"]["radius"] == 0.2 and s.config["output"]["vti"] is True
    with pytest.raises(SceneError, match=r"objects\[0\]\.region\.radius: expected a number > 0"):
        km.Scene.load(path, overrides=[("objects[0].region.radius", "wide")])
    with pytest.raises(ValueError, match="has no item 5"):
        km.Scene.load(path, overrides=[("objects[5].type", "obstacle")])


def test_every_solver_has_an_example():
    solvers = {km.Scene.load(p).solver for p in EXAMPLES.values()}
    assert solvers == set(ADAPTERS), solvers


# ----------------------------------------------------------------------------- example runs

def _png(path):
    from PIL import Image

    with Image.open(path) as im:
        assert im.mode == "RGB"
        return np.asarray(im)


def _ffprobe(path):
    out = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
                          "stream=codec_name,width,height,nb_read_frames", "-of", "json", str(path)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout)["streams"][0]


@pytest.mark.skipif(shutil.which("ffprobe") is None, reason="ffmpeg/ffprobe not installed")
@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_scene_writes_real_files(tmp_path, name):
    import meshio

    frames = 3
    scene = km.Scene.load(EXAMPLES[name], quick=True, overrides=ALL_DATA)
    result = scene.run(tmp_path, frames, progress=False)
    assert result.frames == frames and not result.interrupted and result.steps > 0
    fresh = scene.build()  # the initial state, to check frame 0's files against
    # PNG: decodes to exactly the preview image of the initial state, every frame the same size.
    first = _png(tmp_path / "frames" / "frame_00000.png")
    np.testing.assert_array_equal(first, fresh.image(scene.config["output"]))
    assert first.shape[1] >= scene.config["output"]["width"]
    for k in range(1, frames):
        assert _png(tmp_path / "frames" / f"frame_{k:05d}.png").shape == first.shape
    # MP4: H.264 with every frame, padded to even sizes.
    info = _ffprobe(tmp_path / "video.mp4")
    assert info["codec_name"] == "h264" and int(info["nb_read_frames"]) == frames, info
    assert info["width"] == first.shape[1] + first.shape[1] % 2
    # Data files: re-read with meshio (VTU, PLY) or the VTI reader, point counts and values.
    for item in fresh.data():
        folder = tmp_path / item.name
        if hasattr(item, "fields"):
            back = km.io.read_vtk(folder / f"{item.name}_00000.vti")
            fields, spacing = back["fields"], back["spacing"]
            for key, value in item.fields.items():
                got = fields[key]
                if value.ndim > scene.dim:  # vectors are stored with 3 components
                    got = got.reshape(value.shape[:-1] + (3,))[..., :value.shape[-1]]
                np.testing.assert_array_equal(got.reshape(value.shape), value)
            assert spacing[0] == item.h
            continue
        # Particles a solver reorders are written in their input order (row k = particle k).
        order = np.argsort(item.ids) if item.ids is not None else np.arange(len(item.points))
        mesh = meshio.read(folder / f"{item.name}_00000.vtu")
        assert len(mesh.points) == len(item.points)
        np.testing.assert_array_equal(mesh.points[:, :item.points.shape[1]], item.points[order])
        for kind, cells in item.cells:
            assert any(b.type == kind and np.array_equal(b.data, cells) for b in mesh.cells), kind
        ply = meshio.read(folder / f"{item.name}_00000.ply")
        np.testing.assert_allclose(ply.points[:, :item.points.shape[1]], item.points[order], rtol=1e-15)
        if "velocity" in item.point_data:
            np.testing.assert_array_equal(ply.point_data["velocity_x"], item.point_data["velocity"][order, 0])
        # The series lists every VTU file with its simulated time.
        series = km.io.Series(tmp_path / f"{item.name}.pvd", resume=True).entries
        written = sorted(f"{item.name}/{p.name}" for p in folder.glob("*.vtu"))  # static items: frame 0 only
        assert [f for _, f in series] == written and len(written) in (1, frames)
        assert series[0][0] == 0.0 and all(b[0] > a[0] for a, b in zip(series, series[1:]))
        if item.surface is not None:
            assert len(ply.cells_dict["triangle"]) == len(item.surface)
    with open(tmp_path / "diagnostics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in rows] == list(range(frames))


# ----------------------------------------------------------------------------- resume

@pytest.mark.parametrize("name", ["smoke_plume", "dam_break", "hanging_cloth", "soft_body", "vortex_sheet",
                                  "snowball_jelly", "soft_cube_pile", "cloth_drape", "jelly_stairs"])
def test_resume_is_bit_for_bit(tmp_path, name):
    frames = 5
    scene = km.Scene.load(EXAMPLES[name], quick=True, overrides=[("output.mp4", False)])
    straight = scene.run(tmp_path / "straight", frames, progress=False)
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C after frame 2, as a callback raising it
        scene.run(tmp_path / "resumed", frames, progress=False,
                  on_frame=lambda frame, sim: (_ for _ in ()).throw(KeyboardInterrupt) if frame == 2 else None)
    assert not list((tmp_path / "resumed").rglob("*.tmp")), "a temporary file was left behind"
    assert sorted(p.name for p in (tmp_path / "resumed" / "frames").iterdir()) == \
        [f"frame_{k:05d}.png" for k in range(3)]
    _, meta = output.load_checkpoint(tmp_path / "resumed" / "checkpoint.npz")
    assert meta["frame"] == 2
    resumed = km.Scene.load(EXAMPLES[name], quick=True).run(tmp_path / "resumed", frames, resume=True,
                                                              progress=False)
    assert resumed.new_frames == frames - 3 and resumed.frames == frames
    a, _ = output.load_checkpoint(tmp_path / "straight" / "checkpoint.npz")
    b, _ = output.load_checkpoint(tmp_path / "resumed" / "checkpoint.npz")
    assert sorted(a) == sorted(b)
    for key in a:
        assert np.array_equal(a[key], b[key]), f"{name}: {key} differs after resume"
    assert straight.steps == int(a["steps"])
    last = f"frames/frame_{frames - 1:05d}.png"
    assert (tmp_path / "straight" / last).read_bytes() == (tmp_path / "resumed" / last).read_bytes()


def test_resume_refuses_another_scene(tmp_path):
    km.Scene.load(EXAMPLES["vortex_sheet"], quick=True).run(tmp_path, 2, progress=False)
    other = km.Scene.load(EXAMPLES["vortex_sheet"], quick=True, overrides=[("solver.substeps", 1)])
    with pytest.raises(ValueError, match="different scene"):
        other.run(tmp_path, 3, resume=True, progress=False)
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        other.run(tmp_path / "empty", 3, resume=True, progress=False)


# ----------------------------------------------------------------------------- render modes

SPH_SCENE = """
[scene]
name = "tank"
duration = 0.1
fps = 20
threads = 1
[solver]
type = "sph"
spacing = 0.1
domain = { lower = [0.0, 0.0, 0.0], upper = [1.0, 0.6, 0.6] }
gravity = [0.0, -9.81, 0.0]
[[objects]]
type = "fluid"
region = { shape = "box", lower = [0.0, 0.0, 0.0], upper = [0.4, 0.4, 0.6] }
[output]
mp4 = false
width = 64
"""


MPM_WATER_SCENE = """
[scene]
name = "mpm water"
duration = 0.1
fps = 20
threads = 1
[solver]
type = "mpm"
shape = [16, 12, 12]
h = 0.0625
gravity = [0.0, -9.81, 0.0]
[[objects]]
type = "block"
material = "water"
density = 1000.0
region = { shape = "box", lower = [0.1, 0.1, 0.1], upper = [0.4, 0.4, 0.6] }
[output]
mp4 = false
ply = true
width = 64
render = "preview"
"""


def test_mpm_water_is_drawn_and_exported_as_its_free_surface(tmp_path):
    """An MPM liquid gets the SPH liquid's treatment: a closed surface mesh per frame beside the
    particles, and frames that draw it as water."""
    scene = km.Scene.load(write(tmp_path, MPM_WATER_SCENE, "mpm.toml"))
    scene.run(tmp_path / "out", 2, progress=False)
    surfaces = sorted((tmp_path / "out").rglob("surface*.ply"))
    assert len(surfaces) == 2, sorted(p.name for p in (tmp_path / "out").rglob("*"))
    mesh = km.io.read_vtk(surfaces[0]) if surfaces[0].suffix == ".vtu" else __import__("meshio").read(surfaces[0])
    tris = mesh.cells_dict["triangle"]
    assert len(tris) > 100 and km.mesh.euler_characteristic(tris) == 2
    # The enclosed volume is the particles' (n spacing^3, spacing = h / ppc) to a few percent (the
    # surface bulges between the particles of the corners and edges; km.surface's own tests).
    n = len(scene.build()._water())
    v = mesh.points[tris]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    assert abs(volume / (n * (0.0625 / 2) ** 3) - 1) < 0.05, (volume, n)
    img = __import__("matplotlib.image", fromlist=["x"]).imread(sorted((tmp_path / "out" / "frames").glob("*.png"))[0])
    assert _is_water((img[..., :3] * 255).astype(np.uint8)).mean() > 0.02


def _is_water(img):
    """Pixels of the sph water colour (0.15, 0.4, 0.8) shaded: red well below blue (the grey
    ground and the white-to-light-blue sky have red >= 0.7 blue after tone mapping)."""
    rgb = img.astype(float)
    return (rgb[..., 0] < 0.6 * rgb[..., 2]) & (rgb[..., 2] > 20)


@pytest.mark.parametrize("mode", ["flat", "preview", "pathtrace"])
def test_render_modes_write_frames_of_the_requested_width(tmp_path, mode):
    scene = km.Scene.load(write(tmp_path, SPH_SCENE), overrides=[("output.render", mode), ("output.spp", 2)])
    assert scene.config["output"]["render"] == mode
    scene.run(tmp_path / "out", 2, progress=False)
    for k in range(2):
        img = _png(tmp_path / "out" / "frames" / f"frame_{k:05d}.png")
        assert img.shape[1] == 64 if mode != "flat" else img.shape[1] >= 64, img.shape
        _, counts = np.unique(img.reshape(-1, 3), axis=0, return_counts=True)
        assert len(counts) >= 3 and counts.max() < 0.95 * counts.sum(), \
            f"{mode}: frame {k} has {len(counts)} colours, the commonest on {counts.max() / counts.sum():.3f} of it"
        if mode != "flat":
            assert img.shape[0] == 48, img.shape  # default height: 3/4 of the width
            water = _is_water(img).mean()
            assert 0.01 < water < 0.9, f"{mode}: water covers {water:.3f} of frame {k}"


def test_3d_particle_and_mesh_scenes_default_to_preview_2d_fields_to_flat(tmp_path):
    assert km.Scene.load(write(tmp_path, SPH_SCENE)).config["output"]["render"] == "preview"
    assert km.Scene.load(EXAMPLES["soft_body"]).config["output"]["render"] == "preview"
    assert km.Scene.load(write(tmp_path, GRID_SCENE, "grid.toml")).config["output"]["render"] == "flat"
    assert km.Scene.load(EXAMPLES["vortex_sheet"]).config["output"]["render"] == "flat"
    assert km.Scene.load(EXAMPLES["hanging_cloth"]).config["output"]["render"] == "pathtrace"


def test_pathtrace_frames_are_deterministic_and_follow_the_camera(tmp_path):
    base = [("output.render", "pathtrace"), ("output.spp", 2)]
    for run in ("a", "b"):
        km.Scene.load(write(tmp_path, SPH_SCENE), overrides=base).run(tmp_path / run, 2, progress=False)
    for k in range(2):
        name = f"frames/frame_{k:05d}.png"
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    # An explicit camera straight above the tank, looking down: the water fills the left part
    # of the picture (x to the right), the floor the rest.
    top = base + [("output.camera", {"look_from": [0.5, 3.0, 0.3], "look_at": [0.5, 0.0, 0.3],
                                     "up": [0.0, 0.0, -1.0], "vfov": 14.0})]
    km.Scene.load(write(tmp_path, SPH_SCENE), overrides=top).run(tmp_path / "top", 1, progress=False)
    # The water is a clear absorbing dielectric: at 2 samples a pixel some of its pixels are dark
    # (paths caught by total internal reflection), so the left part's mean colour is tested.
    img = _png(tmp_path / "top" / "frames" / "frame_00000.png")
    left, right = _is_water(img[:, :20].mean(axis=(0, 1))), _is_water(img)[:, 40:].mean()
    assert left and right < 0.05, (img[:, :20].mean(axis=(0, 1)), right)


def test_a_camera_that_cannot_be_built_names_the_key(tmp_path):
    scene = km.Scene.load(write(tmp_path, SPH_SCENE),
                          overrides=[("output.camera", {"look_from": [1.0, 1.0, 1.0], "look_at": [1.0, 1.0, 1.0]})])
    with pytest.raises(SceneError, match=r"output\.camera: look_at: must differ from look_from"):
        scene.run(tmp_path / "out", 1, progress=False)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "frame.png"
    with pytest.raises(KeyboardInterrupt):
        with output.atomic_path(target) as tmp:
            tmp.write_bytes(b"half a frame")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    output.write_png(target, np.zeros((4, 6, 3), np.uint8))
    output.write_png(target, np.full((4, 6, 3), 200, np.uint8))  # replaces the file
    assert [p.name for p in tmp_path.iterdir()] == ["frame.png"]
    assert (_png(target) == 200).all()


# ----------------------------------------------------------------------------- sweep

def test_sweep_on_a_local_dask_cluster(tmp_path):
    pytest.importorskip("dask.distributed")
    from kinema.scenes.sweep import parse_param, sweep

    key, values = parse_param("substeps=1,3")
    assert (key, values) == ("substeps", [1, 3])  # a bare key: resolved against the scene
    assert parse_param("solver.resolution=[8,8],[16,16]")[1] == [[8, 8], [16, 16]]
    stale = tmp_path / "run_005"  # a run of an earlier, larger sweep into the same folder
    stale.mkdir()
    (stale / "run.json").write_text("{}")
    rows = sweep(EXAMPLES["vortex_sheet"], {key: values}, tmp_path, frames=3, quick=True,
                 workers=1, processes=False, log=lambda m: None)
    assert sorted(p.name for p in tmp_path.glob("run_*")) == ["run_000", "run_001"]
    with open(tmp_path / "sweep.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 2 == len(rows)
    assert [int(r["solver.substeps"]) for r in table] == [1, 3]
    # 3 frames = 2 frame advances of `substeps` RK4 steps each.
    assert [int(r["steps"]) for r in table] == [2, 6]
    assert all(float(r["wall_seconds"]) > 0 and r["metric"] == r["impulse_drift"] for r in table)
    assert (tmp_path / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("run_*/*.tmp"))
    assert (tmp_path / "run_001" / "video.mp4").exists() or shutil.which("ffmpeg") is None


def test_meshes_from_files(tmp_path):
    import meshio

    V, T = km.fem.box_mesh([0, 0, 0], [1.0, 0.2, 0.2], (4, 1, 1))
    meshio.write_points_cells(tmp_path / "beam.vtu", V, [("tetra", T)])
    meshio.write_points_cells(tmp_path / "sheet.obj", V[:4], [("triangle", np.array([[0, 1, 2], [1, 3, 2]]))])
    fem = write(tmp_path, """
[scene]
name = "beam from a file"
duration = 0.1
threads = 1
[solver]
type = "fem"
gravity = [0.0, 0.0, -9.81]
[[objects]]
type = "mesh"
file = "beam.vtu"
scale = 2.0
youngs_modulus = 1e5
poisson_ratio = 0.3
density = 1000.0
fixed = [{ shape = "box", lower = [-0.1, -0.1, -0.1], upper = [0.01, 1.0, 1.0] }]
""", "fem.toml")
    sim = km.Scene.load(fem).build()
    np.testing.assert_array_equal(sim.body.x, 2.0 * V)
    np.testing.assert_array_equal(sim.body.elements, T)
    assert set(sim.body.fixed) == set(np.flatnonzero(V[:, 0] == 0))
    springs = write(tmp_path, """
[scene]
name = "springs from a file"
duration = 0.1
[solver]
type = "massspring"
[[objects]]
type = "mesh"
file = "sheet.obj"
stiffness = 10.0
""", "ms.toml")
    sim = km.Scene.load(springs).build()
    assert sorted(map(tuple, sim.body.springs)) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    bad = write(tmp_path, fem.read_text().replace("beam.vtu", "missing.vtu"), "bad.toml")
    with pytest.raises(SceneError, match=r"objects\[0\]\.file: cannot read"):
        km.Scene.load(bad).build()


def test_3d_grid_scene(tmp_path):
    text = GRID_SCENE.replace("[16, 16]", "[8, 8, 6]").replace("[0.5, 0.5]", "[0.5, 0.5, 0.3]") \
        .replace("[0.1, 0.1]", "[0.1, 0.1, 0.1]").replace("[0.3, 0.3]", "[0.3, 0.3, 0.3]") \
        .replace("[1.0, 0.0]", "[1.0, 0.0, 0.0]")
    scene = km.Scene.load(write(tmp_path, text), overrides=[("output.vti", True), ("output.mp4", False)])
    assert scene.dim == 3
    scene.run(tmp_path / "out", 2, progress=False)
    fields = km.io.read_vtk(tmp_path / "out" / "grid" / "grid_00001.vti")["fields"]
    assert fields["pressure"].shape == (8, 8, 6) and fields["velocity"].shape == (8, 8, 6, 3)
    # 3D grids are ray-marched (render3d.smoke_image): output.width wide, 3/4 as high.
    assert _png(tmp_path / "out" / "frames" / "frame_00001.png").shape[:2] == (480, 640)


def test_sweep_keys_reach_objects_and_the_plot_names_the_metric(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from kinema.scenes.sweep import _plot, resolve_key

    assert resolve_key(EXAMPLES["soft_body"], "youngs_modulus") == "objects[0].youngs_modulus"
    assert resolve_key(EXAMPLES["soft_body"], "substeps") == "solver.substeps"
    assert resolve_key(EXAMPLES["soft_body"], "objects[0].density") == "objects[0].density"
    with pytest.raises(ValueError, match="--param nothing: neither a fem solver option nor a key"):
        resolve_key(EXAMPLES["soft_body"], "nothing")
    two = write(tmp_path, GRID_SCENE, "two.toml")  # two objects with a region each
    with pytest.raises(ValueError, match=r"several objects have it \(objects\[0\]\.region, objects\[1\]\.region\)"):
        resolve_key(two, "region")
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    rows = [{"solver.substeps": s, "wall_seconds": 0.1 * s, "metric": 1.0 / s} for s in (1, 2)]
    _plot(tmp_path / "s.png", rows, ["solver.substeps"], "impulse_drift")
    assert figures[0].axes[1].get_ylabel() == "impulse_drift"
    assert figures[0].axes[0].get_xlabel() == "solver.substeps"


def test_one_up_axis_in_every_shipped_scene():
    """y is up everywhere (docs/guide/conventions.md): every shipped scene with gravity pulls
    along -y, and the default 3D view has y up on screen. Deformable scenes once pulled along
    -z while the renderer drew y up, so a jelly fell sideways through the drawn floor."""
    from kinema.scenes import render3d

    for path in sorted(Path(km.__file__).parent.joinpath("scenes", "examples").glob("*.toml")):
        scene = km.Scene.load(path, quick=True)
        g = scene.config["solver"].get("gravity")
        if g is not None and any(g):
            assert g[1] < 0 and all(c == 0 for i, c in enumerate(g) if i != 1), (path.stem, g)
        assert scene.config["output"].get("view") in (None, [0, 1], (0, 1)), path.stem
    right, up, toward = render3d._basis((0, 1))
    np.testing.assert_array_equal(up, [0, 1, 0])
    sim = km.mpm.Simulation((4, 4, 4), 0.25)  # gravity=None: no gravity, as in every module
    assert not np.asarray(sim.gravity).any()


MPM_SAND_SCENE = """
[scene]
name = "mpm sand"
duration = 0.01
fps = 100
threads = 1
[solver]
type = "mpm"
shape = [16, 16]
h = 0.0625
gravity = [0.0, -9.81]
[[objects]]
type = "block"
material = "sand"
density = 1600.0
friction_law = "{law}"
{extra}
region = {{ shape = "box", lower = [0.1, 0.0], upper = [0.4, 0.3] }}
[output]
mp4 = false
width = 64
"""


def test_mpm_scene_sand_takes_the_mu_i_law_and_its_parameters(tmp_path):
    text = MPM_SAND_SCENE.format(law="mu_i", extra="mu_s = 0.5\nmu_2 = 0.8\nI0 = 0.3\n"
                                 "grain_diameter = 0.002\ngrain_density = 2650.0")
    material = km.Scene.load(write(tmp_path, text, "sand.toml")).build().sim.materials[0]
    assert (material.friction_law, material.mu_s, material.mu_2, material.I0) == ("mu_i", 0.5, 0.8, 0.3)
    assert (material.grain_diameter, material.grain_density) == (0.002, 2650.0)
    constant = MPM_SAND_SCENE.format(law="constant", extra="friction_angle = 30.0")
    assert km.Scene.load(write(tmp_path, constant, "c.toml")).build().sim.materials[0].friction_law == "constant"


def test_mpm_scene_refuses_mu_i_parameters_on_the_constant_law(tmp_path):
    text = MPM_SAND_SCENE.format(law="constant", extra="friction_angle = 30.0\nmu_s = 0.5")
    with pytest.raises(ValueError, match=r"objects\[0\].*mu_s"):
        km.Scene.load(write(tmp_path, text, "bad.toml")).build()
    with pytest.raises(ValueError, match="friction_law"):
        km.Scene.load(write(tmp_path, MPM_SAND_SCENE.format(law="coulomb", extra=""), "bad2.toml"))
