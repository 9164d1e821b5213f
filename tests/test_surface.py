"""Free-surface reconstruction (km.surface) of particle liquids: topology, volume, position."""

import numpy as np
import pytest

import kinema as km

pytest.importorskip("skimage", reason="the surface extra is not installed (pip install 'kinema[surface]')")
pytest.importorskip("pysplashsurf", reason="the surface extra is not installed (pip install 'kinema[surface]')")

S = 0.025  # particle spacing [m]


def lattice_ball(radius_cells, centre=(0.0, 0.0, 0.0)):
    """Particles of a cubic lattice of spacing S inside a sphere of radius radius_cells * S."""
    k = np.arange(-radius_cells - 1, radius_cells + 2) * S
    x = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    return x[np.linalg.norm(x, axis=1) < radius_cells * S] + np.asarray(centre)


@pytest.mark.parametrize("method", km.surface.METHODS)
def test_sphere_of_particles_closed_with_its_volume_and_radius(method):
    centre = np.array([0.31, -0.12, 0.07])  # off the reconstruction grids' axes
    x = lattice_ball(12, centre)
    mesh = km.surface.reconstruct(x, S, method=method)
    # Closed (every edge in two triangles, opposite directions) and a sphere's topology.
    assert mesh.is_closed()
    assert mesh.euler_characteristic() == 2
    # Each particle stands for a cube S^3: their union is the voxelised ball of volume n S^3.
    # The smoothing shifts the level set of a ball inwards by about sigma^2 / R (sigma = 0.6 S,
    # R = 12 S: 0.03 S, 0.75% of the volume); 2% leaves room for the lattice's ripple.
    v_particles = len(x) * S**3
    assert abs(mesh.volume() / v_particles - 1) < 0.02, (mesh.volume(), v_particles)
    # The voxelised ball lies within sqrt(3)/2 S (half a cube's diagonal) of the sphere of the
    # same volume; the smoothed surface must lie no farther, and on average within S / 4.
    r_eq = (3 * v_particles / (4 * np.pi)) ** (1 / 3)
    dist = np.linalg.norm(mesh.vertices - centre, axis=1) - r_eq
    assert np.abs(dist).max() < np.sqrt(3) / 2 * S, np.abs(dist).max() / S
    assert np.sqrt(np.mean(dist**2)) < 0.25 * S, np.sqrt(np.mean(dist**2)) / S


@pytest.mark.parametrize("method", km.surface.METHODS)
def test_two_drops_two_closed_surfaces_and_a_slab_face_half_a_spacing_out(method):
    x = np.concatenate([lattice_ball(6), lattice_ball(6, (0.5, 0.0, 0.0))])
    mesh = km.surface.reconstruct(x, S, method=method)
    assert mesh.is_closed() and mesh.euler_characteristic() == 4
    # A slab of 8 layers: its top face lies half a spacing above the top layer (volume n S^3).
    k = np.arange(24) * S
    slab = np.stack(np.meshgrid(k, k, np.arange(8) * S, indexing="ij"), -1).reshape(-1, 3)
    m = km.surface.reconstruct(slab, S, method=method)
    top = m.vertices[(np.abs(m.vertices[:, 0] - 11.5 * S) < 4 * S) & (np.abs(m.vertices[:, 1] - 11.5 * S) < 4 * S)
                     & (m.vertices[:, 2] > 4 * S)]
    assert len(top) > 10
    # splashsurf's 0.6 level of the kernel-sum colour field sits a little inside the 1/2 level.
    assert np.abs(top[:, 2] - 7.5 * S).max() < 0.15 * S, (top[:, 2].min() / S, top[:, 2].max() / S)


def test_mesh_files_ply_and_obj(tmp_path):
    meshio = pytest.importorskip("meshio")
    mesh = km.surface.reconstruct(lattice_ball(5), S, method="marching_cubes")
    for suffix in (".ply", ".obj"):
        path = mesh.write(tmp_path / f"surface{suffix}")
        back = meshio.read(path)
        np.testing.assert_allclose(back.points, mesh.vertices, rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(back.cells_dict["triangle"], mesh.triangles)


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="points"):
        km.surface.reconstruct(np.zeros((4, 2)), S)
    with pytest.raises(ValueError, match="points"):
        km.surface.reconstruct(np.full((4, 3), np.nan), S)
    with pytest.raises(ValueError, match="spacing"):
        km.surface.reconstruct(np.zeros((4, 3)), -1.0)
    with pytest.raises(ValueError, match="method"):
        km.surface.reconstruct(np.zeros((4, 3)), S, method="poisson")
    with pytest.raises(ValueError, match="path"):
        km.surface.Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]])).write("x.stl")
    assert len(km.surface.reconstruct(np.zeros((0, 3)), S).triangles) == 0


def test_a_smoothing_too_wide_for_the_liquid_is_named():
    """A Gaussian 6 spacings wide leaves a small drop's volume fraction below iso everywhere:
    the error names iso and the smoothing (it was scikit-image's bare "Surface level must be
    within volume data range")."""
    with pytest.raises(ValueError, match=r"^iso: .*smoothing = 0\.15 m"):
        km.surface.reconstruct(lattice_ball(2), S, smoothing=6 * S)
    with pytest.raises(ValueError, match="^iso: "):
        km.surface.reconstruct(lattice_ball(3), S, iso=2.0)


def test_a_wide_smoothing_on_a_large_grid_stops_at_ctrl_c(monkeypatch):
    """smoothing = 1 m around a 0.3 m ball of spacing 0.05 is a Gaussian of 40 cells on 1.8e7
    cells: tens of seconds in scipy's filter, whose C loop does not look for Ctrl-C (the API
    fuzz found SIGINT unanswered: tests/fuzz, surface.reconstruct[smoothing=np.array(1.0)]).
    The filter now runs as short 1D passes over slabs of the grid: SIGINT, sent here as the
    second pass starts, stops the run within a second, a few passes later."""
    import os
    import signal
    import time

    import scipy.ndimage

    original = scipy.ndimage.gaussian_filter1d
    calls, sent = [], []

    def counted(*args, **kwargs):
        calls.append(time.perf_counter())
        if len(calls) == 2:
            sent.append(time.perf_counter())
            os.kill(os.getpid(), signal.SIGINT)
        return original(*args, **kwargs)

    monkeypatch.setattr(scipy.ndimage, "gaussian_filter1d", counted)
    ball = km.mpm.sphere([0.0, 0.0, 0.0], 0.3, 0.05)
    # Background shells start with SIGINT ignored: install Python's handler, as a terminal has.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            km.surface.reconstruct(ball, 0.05, smoothing=1.0)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert sent and time.perf_counter() - sent[0] < 1.0 and len(calls) <= 4, calls


def test_marching_cubes_over_slabs_is_the_whole_call():
    """Marching cubes runs over slabs of the grid (so that Ctrl-C is answered between them):
    cut into slabs of a few layers, or of one layer each, the mesh is scikit-image's whole call's
    (the same vertices matched one to one, the same triangles), its vertices within float32
    rounding of the whole call's. scikit-image rounds a vertex's cell coordinate (< n, the
    grid's largest index) to float32, the slab at its index in the slab and the whole call at its
    index in the grid: each within half an ulp, an ulp at most 2^-23 n."""
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    field, _ = km.surface.volume_fraction(lattice_ball(6), S, 0.5 * S, 0.6 * S)
    v, t, _, _ = marching_cubes(field, 0.5, allow_degenerate=False)
    whole = km.surface._outward(v, t)
    bound = 2.0**-23 * max(field.shape)
    for cells in (8 * field[0].size, field[0].size):  # slabs of 8 layers, of 1 layer
        sliced = km.surface._outward(*km.surface._level_set(field, 0.5, marching_cubes, cells))
        assert sliced.is_closed() and sliced.euler_characteristic() == whole.euler_characteristic() == 2
        distance, match = cKDTree(whole.vertices).query(sliced.vertices)
        assert len(sliced.vertices) == len(whole.vertices) and len(np.unique(match)) == len(match)
        assert distance.max() <= bound, (distance.max(), bound)
        same = np.unique(np.sort(match[sliced.triangles], axis=1), axis=0)
        np.testing.assert_array_equal(same, np.unique(np.sort(whole.triangles, axis=1), axis=0))


def test_marching_cubes_on_a_large_grid_stops_at_ctrl_c(monkeypatch, ctrl_c_delay):
    """scikit-image's marching cubes is a C loop that does not look for Ctrl-C: on a 256^3 grid
    of a gyroid-like field (2.5 million vertices) it took 1.9 CPU seconds (8.7 s of wall time on
    a loaded machine) in one call. Over slabs of about a million cells each call is a
    sixteenth of that (0.12 CPU s): SIGINT, sent after 0.1 CPU seconds of the run, must stop it
    within 0.5 CPU seconds (CPU time, which other processes' load does not stretch), where the
    one call ran on for 1.0 to 1.6 s. The signal comes from the kernel's CPU timer: the call holds the
    GIL, so a timer thread could not send it until the call returned. The smoothed field is
    handed in directly, so the signal lands in the marching cubes, not in the smoothing."""
    a = np.linspace(0.0, 16 * np.pi, 256, dtype=np.float32)
    sin, cos = np.sin(a), np.cos(a)
    field = (sin[:, None, None] * cos[None, :, None] + sin[None, :, None] * cos[None, None, :]
             + sin[None, None, :] * cos[:, None, None])
    monkeypatch.setattr(km.surface, "volume_fraction", lambda x, s, c, sigma: (field, np.zeros(3)))
    cpu = ctrl_c_delay(lambda: km.surface.reconstruct(lattice_ball(2), S, iso=0.5), after=0.1, on_cpu=True)
    assert cpu < 0.5, cpu


def test_example_water_surface_runs(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "examples" / "water_surface.py"
    subprocess.run([sys.executable, str(example), "--out", str(tmp_path), "--frames", "2", "--spacing", "0.04",
                    "--spp", "1", "--width", "32"], check=True, timeout=300)
    assert (tmp_path / "water.png").stat().st_size > 100
    meshio = pytest.importorskip("meshio")
    mesh = meshio.read(tmp_path / "surface_002.ply")
    assert len(mesh.cells_dict["triangle"]) > 100
