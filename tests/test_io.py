"""kinema.io: files read back by an independent reader (meshio) and by km.io.read_vtk, the
stable particle order of a reordering SPH fluid, series with times, compression, permissions,
and km.massspring.cloth's triangles and planes."""

import json
import os
import stat
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

import kinema as km


def test_particles_vtu_and_ply_read_back_by_meshio(tmp_path):
    rng = np.random.default_rng(1)
    x = rng.random((50, 3))
    v = rng.standard_normal((50, 3))
    rho = rng.random(50)
    for compress in (True, False):
        path = km.io.write_particles(tmp_path / f"p{compress}.vtu", x, {"velocity": v, "density": rho},
                                     compress=compress)
        m = meshio.read(path)
        np.testing.assert_array_equal(m.points, x)
        np.testing.assert_array_equal(m.point_data["velocity"], v)
        np.testing.assert_array_equal(m.point_data["density"], rho)
        ours = km.io.read_vtk(path)
        np.testing.assert_array_equal(ours["points"], x)
        assert ours["cells"][0][0] == "vertex" and len(ours["cells"][0][1]) == 50
    m = meshio.read(km.io.write_particles(tmp_path / "p.ply", x[:, :2], {"velocity": v[:, :2]}))
    np.testing.assert_array_equal(m.points[:, :2], x[:, :2])
    np.testing.assert_array_equal(m.points[:, 2], 0.0)
    np.testing.assert_array_equal(m.point_data["velocity_x"], v[:, 0])


def test_sph_fluid_is_written_in_its_input_order(tmp_path):
    s = 0.05
    start = km.sph.block([0, 0], [0.5, 0.5], s)
    fluid = km.sph.Fluid(start, s, method="wcsph", gravity=(0, -9.81), domain=([0, 0], [1.0, 0.8]), reorder_every=1)
    fluid.step(1e-3)
    fluid.step(1e-3)
    ids = np.asarray(fluid.ids)
    assert not np.array_equal(ids, np.arange(len(ids))), "the fluid did not reorder: the test would prove nothing"
    path = km.io.write_particles(tmp_path / "f.vtu", fluid)
    m = meshio.read(path)
    expected = np.empty_like(np.asarray(fluid.x))
    expected[ids] = fluid.x
    np.testing.assert_array_equal(m.points[:, :2], expected)
    np.testing.assert_array_equal(m.point_data["id"], np.arange(len(ids)))
    # Each particle has moved by less than a spacing from where it was given: row k is particle k.
    assert np.abs(m.points[:, :2] - start).max() < s
    for name in ("velocity", "density", "pressure"):
        assert name in m.point_data
    with pytest.raises(ValueError, match="ids: expected a permutation"):
        km.io.write_particles(tmp_path / "g.vtu", np.zeros((3, 2)), ids=[0, 0, 1])


def test_meshes_vtu_ply_obj(tmp_path):
    V, T = km.fem.box_mesh([0, 0, 0], [1, 0.5, 0.5], (3, 2, 2))
    path = km.io.write_mesh(tmp_path / "b.vtu", V, T, point_data={"y": V[:, 1]},
                            cell_data={"e": np.arange(len(T))})
    m = meshio.read(path)
    np.testing.assert_array_equal(m.cells_dict["tetra"], T)
    np.testing.assert_array_equal(m.cell_data["e"][0], np.arange(len(T)))
    back = km.io.read_vtk(path)
    np.testing.assert_array_equal(back["cells"][0][1], T)
    cloth = km.massspring.cloth(4, 3, 1.0)
    for suffix in ("ply", "obj"):
        m = meshio.read(km.io.write_mesh(tmp_path / f"c.{suffix}", cloth.x, cloth.triangles))
        np.testing.assert_allclose(m.points, cloth.x)
        np.testing.assert_array_equal(m.cells_dict["triangle"], cloth.triangles)
    with pytest.raises(ValueError, match="triangles only"):
        km.io.write_mesh(tmp_path / "b.ply", V, T)
    with pytest.raises(ValueError, match=r"vertex indices must lie in \[0, 12\)"):
        km.io.write_mesh(tmp_path / "c.vtu", cloth.x, cloth.triangles + 1)
    with pytest.raises(ValueError, match="path: expected a file name ending in"):
        km.io.write_mesh(tmp_path / "c.stl", cloth.x, cloth.triangles)
    with pytest.raises(ValueError, match="points: contains NaN"):
        km.io.write_mesh(tmp_path / "c.vtu", np.full((3, 3), np.nan), [[0, 1, 2]])


@pytest.mark.parametrize("shape", [(5, 7), (4, 5, 6)])
def test_grid_round_trip_and_layout(tmp_path, shape):
    rng = np.random.default_rng(2)
    q = rng.random(shape)
    v = rng.random(shape + (len(shape),))
    path = km.io.write_grid(tmp_path / "g.vti", {"q": q, "v": v}, 0.25, origin=(1.0, 2.0, 3.0))
    back = km.io.read_vtk(path)
    shape3 = shape + (1,) * (3 - len(shape))
    np.testing.assert_array_equal(back["fields"]["q"], q.reshape(shape3))
    np.testing.assert_array_equal(back["fields"]["v"][..., :len(shape)], v.reshape(shape3 + (len(shape),)))
    np.testing.assert_array_equal(back["fields"]["v"][..., len(shape):], 0.0)
    assert back["spacing"] == [0.25] * 3 and back["origin"] == [1.0, 2.0, 3.0]
    # VTK's order: x runs fastest in the file. Cell (1, 0, 0) is the file's second value.
    root = ET.parse(path).getroot()
    assert root.get("compressor") == "vtkZLibDataCompressor"
    assert root.find("ImageData").get("WholeExtent") == " ".join(f"0 {n}" for n in shape3)


def test_compression_of_smoke_frames():
    """The issue's case: four 32x48x32 smoke frames were 15 MB uncompressed. A plume occupies
    a small part of the box; the rest is zero and compresses away."""
    import tempfile

    sim = km.grid.Fluid((32, 48, 32), h=1 / 32, density=True)
    sim.density[12:20, :10, 12:20] = np.random.default_rng(3).random((8, 10, 8))
    fields = {"density": sim.density, "pressure": sim.pressure}
    with tempfile.TemporaryDirectory() as tmp:
        packed = km.io.write_grid(os.path.join(tmp, "a.vti"), fields, sim.h).stat().st_size
        raw = km.io.write_grid(os.path.join(tmp, "b.vti"), fields, sim.h, compress=False).stat().st_size
    assert raw > 2 * 8 * 32 * 48 * 32  # two float64 fields, base64 adds a third
    assert packed < raw / 20, (packed, raw)


def test_grid_in_single_precision(tmp_path):
    q = np.random.default_rng(4).standard_normal((6, 5, 4))
    full = km.io.write_grid(tmp_path / "d.vti", {"q": q}, 0.5)
    half = km.io.write_grid(tmp_path / "s.vti", {"q": q}, 0.5, single=True)
    back = km.io.read_vtk(half)["fields"]["q"]
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, q, rtol=2.0**-24)  # float32 rounding, half an ulp
    assert half.stat().st_size < 0.7 * full.stat().st_size


def test_series_pvd_and_json(tmp_path):
    series = km.io.Series(tmp_path / "s.pvd")
    for k, t in enumerate([0.0, 0.04, 0.1]):
        series.add(t, tmp_path / "d" / f"d_{k}.vtu")
    root = ET.parse(tmp_path / "s.pvd").getroot()
    rows = [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]
    assert rows == [(0.0, "d/d_0.vtu"), (0.04, "d/d_1.vtu"), (0.1, "d/d_2.vtu")]
    # Resumed from t = 0.04: later entries are replaced.
    again = km.io.Series(tmp_path / "s.pvd", resume=True)
    again.add(0.04, tmp_path / "d" / "d_1.vtu")
    assert [t for t, _ in again.entries] == [0.0, 0.04]
    js = km.io.Series(tmp_path / "s.series")
    js.add(0.5, tmp_path / "a.ply")
    assert json.loads((tmp_path / "s.series").read_text())["files"] == [{"name": "a.ply", "time": 0.5}]
    with pytest.raises(ValueError, match="time: expected a finite number"):
        js.add(float("nan"), tmp_path / "a.ply")


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_files_follow_the_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        path = km.io.write_particles(tmp_path / "p.vtu", np.zeros((2, 3)))
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask


def test_cloth_triangles_planes_and_origin():
    cloth = km.massspring.cloth(4, 3, (3.0, 2.0), plane="xz", origin=(1.0, 2.0, 3.0))
    x, springs = cloth  # the API contract's pair
    assert x.shape == (12, 3) and springs.shape[1] == 2
    np.testing.assert_allclose(x[:, 1], 2.0)  # the xz plane through the origin
    np.testing.assert_allclose([x[:, 0].min(), x[:, 0].max(), x[:, 2].min(), x[:, 2].max()], [1, 4, 3, 5])
    T = cloth.triangles
    assert T.shape == (2 * 3 * 2, 3)
    # The triangles tile the rectangle once: their areas add up to it, none is degenerate.
    e1, e2 = x[T[:, 1]] - x[T[:, 0]], x[T[:, 2]] - x[T[:, 0]]
    normals = np.cross(e1, e2)
    np.testing.assert_allclose(0.5 * np.linalg.norm(normals, axis=1).sum(), 3.0 * 2.0)
    # One orientation for all: e_x cross e_z = -y.
    np.testing.assert_array_less(normals[:, 1], 0.0)
    assert np.unique(np.sort(T, axis=1), axis=0).shape[0] == len(T)
    x3, s3, kinds = km.massspring.cloth(4, 3, 1.0, return_kinds=True)
    assert len(kinds) == len(s3)
    with pytest.raises(ValueError, match="plane: expected one of"):
        km.massspring.cloth(3, 3, 1.0, plane="xw")
    with pytest.raises(ValueError, match="plane"):
        km.massspring.cloth(3, 3, 1.0, dim=2, plane="xz")
    with pytest.raises(ValueError, match="origin: expected 3 components"):
        km.massspring.cloth(3, 3, 1.0, origin=(0, 0))
