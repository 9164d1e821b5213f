"""The live viewer (km.viewer, Polyscope) under a virtual X display with Mesa's OpenGL.

A display is made with Xvfb when none is set (scripts/setup.sh installs Debian's xvfb and
libgl1-mesa-dri); the tests skip, saying why, only where neither a display nor Xvfb exists.
"""

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

import kinema as km

pytest.importorskip("polyscope", reason="the viewer extra is not installed (pip install 'kinema[viewer]')")

from kinema import viewer as kv  # noqa: E402


@pytest.fixture(scope="module")
def display():
    """A display for the module: the one set, or a fresh Xvfb (stopped at the end)."""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("no display and no Xvfb to make one (Debian: apt-get install xvfb libgl1-mesa-dri)")
    proc = None
    for number in range(90, 120):
        if os.path.exists(f"/tmp/.X11-unix/X{number}") or os.path.exists(f"/tmp/.X{number}-lock"):
            continue
        proc = subprocess.Popen([xvfb, f":{number}", "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for _ in range(100):
            if os.path.exists(f"/tmp/.X11-unix/X{number}") or proc.poll() is not None:
                break
            time.sleep(0.05)
        if proc.poll() is None:
            break
        proc = None
    if proc is None:
        pytest.skip("Xvfb would not start on any display :90-:119")
    os.environ["DISPLAY"] = f":{number}"
    try:
        yield os.environ["DISPLAY"]
    finally:
        import polyscope as ps

        if kv._initialised:
            ps.shutdown()
            kv._initialised = False
        del os.environ["DISPLAY"]
        proc.terminate()
        proc.wait(timeout=10)


def _bluish(img):
    """Pixels of the fluid's colour (kv.FLUID_COLOR, shaded): blue well above red."""
    rgb = img.astype(int)
    return (rgb[..., 2] > rgb[..., 0] + 60) & (rgb[..., 2] > 90)


@pytest.mark.parametrize("points", ["polyscope", "splat"])
def test_screenshot_shows_the_particles_inside_their_projected_box(display, points):
    v = kv.Viewer("dam_break", quick=True, quantity=kv.NONE, width=640, height=480, points=points)
    try:
        v.step(3)
        img = v.screenshot()
        assert img.shape == (480, 640, 3)
        x = v.source.sim.fluid.x
        r = 0.5 * v.source.sim.spacing
        corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], float)
        lo, hi = x.min(0) - r, x.max(0) + r
        col, row = v.project(lo + corners * (hi - lo))
        c0, c1 = int(np.floor(col.min())) - 2, int(np.ceil(col.max())) + 2
        r0, r1 = int(np.floor(row.min())) - 2, int(np.ceil(row.max())) + 2
        blue = _bluish(img)
        inside = np.zeros_like(blue)
        inside[max(r0, 0):r1, max(c0, 0):c1] = True
        # The block of water covers much of its box's projection; nothing blue lies outside it.
        assert blue[inside].mean() > 0.3, (blue[inside].mean(), (r0, r1, c0, c1))
        assert blue[~inside].sum() == 0, np.argwhere(blue & ~inside)[:5]
        # The background (the corners of the view) is the viewer's, not the fluid's.
        assert not blue[:20, -20:].any() and not blue[-20:, -20:].any()
    finally:
        v.close()


def test_pause_step_reset_and_keys_change_the_state_as_they_should(display):
    v = kv.Viewer("dam_break", quick=True, paused=True, width=320, height=240)
    try:
        x0 = v.source.sim.fluid.x.copy()
        fps = v.source.scene.fps
        v.tick(2)  # paused: drawn, not advanced
        assert v.frame == 0 and v.time == 0.0
        v.step()
        assert v.frame == 1 and v.time == pytest.approx(1 / fps)
        v.handle_key("n")
        assert v.frame == 2 and v.time == pytest.approx(2 / fps)
        assert v.steps_per_second > 0
        v.handle_key("space")  # run
        assert not v.paused
        v.tick(2)
        assert v.frame == 4
        v.handle_key("space")
        assert v.paused
        assert not np.array_equal(v.source.sim.fluid.x, x0)
        v.handle_key("r")
        assert v.frame == 0 and v.time == 0.0
        np.testing.assert_array_equal(v.source.sim.fluid.x, x0)
        with pytest.raises(ValueError, match="key"):
            v.handle_key("q")
    finally:
        v.close()


@pytest.mark.parametrize("points", ["polyscope", "splat"])
def test_quantity_picker_recolours_the_particles(display, points):
    v = kv.Viewer("dam_break", quick=True, paused=True, width=320, height=240, points=points)
    try:
        assert v.quantities[0] == kv.NONE and {"velocity", "density"} <= set(v.quantities)
        v.step(4)
        v.quantity = kv.NONE
        plain = v.screenshot()
        v.quantity = "density"
        coloured = v.screenshot()
        # Solid blue everywhere the fluid is, against the colormap's spread of hues.
        assert _bluish(plain).sum() > 3 * max(1, _bluish(coloured).sum()) or \
            np.abs(plain.astype(int) - coloured).sum(axis=2).astype(bool).mean() > 0.02
        with pytest.raises(ValueError, match="quantity"):
            v.quantity = "no such thing"
    finally:
        v.close()


def test_splatted_particles_follow_the_camera_and_hide_behind_each_other(display):
    """Splats are made for the camera of the frame: orbiting while paused redraws them where the
    particles now project; the particle nearest the eye is the one seen where two overlap."""
    v = kv.Viewer("dam_break", quick=True, paused=True, quantity=kv.NONE, width=320, height=240,
                  points="splat")
    try:
        before = _bluish(v.screenshot())
        v.ps.look_at((3.0, 2.0, -2.5), (0.4, 0.2, 0.2))  # from behind, the other side
        after = _bluish(v.screenshot())
        x = v.source.sim.fluid.x
        col, row = v.project(x)
        inside = (col >= 0) & (col < 320) & (row >= 0) & (row < 240)
        seen = after[row[inside].astype(int), col[inside].astype(int)]
        # Most particle centres land on blue pixels in the new view, and the view changed.
        assert seen.mean() > 0.8, seen.mean()
        assert (before != after).mean() > 0.02
    finally:
        v.close()
    # Two particles on the view axis: the nearer, a solid one (grey), hides the fluid (blue).
    near = kv.CallbackSource(lambda: 1, lambda: {"fluid": (np.array([[0.0, 0.0, 0.0]]), {"speed": np.ones(1)}),
                                                  "wall": (np.array([[0.0, 0.0, 0.5]]), {})}, name="pair")
    v = kv.Viewer(near, quantity=kv.NONE, point_radius=0.2, width=200, height=200, points="splat")
    try:
        v.ps.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0))
        img = v.screenshot()
        col, row = v.project(np.array([[0.0, 0.0, 0.5]]))
        centre = img[int(row[0]), int(col[0])].astype(int)
        assert not _bluish(img[int(row[0]) - 2:int(row[0]) + 3, int(col[0]) - 2:int(col[0]) + 3]).any()
        assert abs(centre[0] - centre[2]) < 40 and centre.sum() > 150, centre  # grey, lit
    finally:
        v.close()


def test_viewer_point_options_are_checked():
    with pytest.raises(ValueError, match="points"):
        kv.Viewer("dam_break", quick=True, points="quads")
    with pytest.raises(ValueError, match="splat_scale"):
        kv.Viewer("dam_break", quick=True, splat_scale=0)


def test_2d_grid_field_drawn_as_an_image(display):
    v = kv.Viewer("smoke_plume", quick=True, width=320, height=240, cmap="inferno")
    try:
        v.step(2)
        assert v.quantity in v.quantities and "density" in v.quantities
        img = v.screenshot()
        g = v._items[0]
        nx, ny = next(f for f in g.fields.values() if f.ndim == 2).shape
        col, row = v.project(np.array([[0, 0], [nx * g.h, ny * g.h]], float))
        c0, c1 = sorted(col.astype(int))
        r0, r1 = sorted(row.astype(int))
        background = img[2, 2].astype(int)
        inside = img[r0 + 3:r1 - 3, c0 + 3:c1 - 3].astype(int)
        outside = np.concatenate([img[:, :max(c0 - 3, 0)].reshape(-1, 3), img[:, c1 + 3:].reshape(-1, 3)]).astype(int)
        assert c1 - c0 > 50 and r1 - r0 > 50
        # Inside the grid's square the field's colours, outside only the background.
        assert (np.abs(inside - background).sum(axis=2) > 30).mean() > 0.9
        assert (np.abs(outside - background).sum(axis=1) > 30).mean() < 0.01
    finally:
        v.close()


def test_finished_run_scrubbed_from_its_files(display, tmp_path):
    scene = km.Scene.load(km.scenes.resolve("dam_break"), quick=True,
                          overrides=[("output.every", 1), ("output.png", False), ("output.mp4", False)])
    scene.run(tmp_path, 3, progress=False)
    src = kv.RunSource(tmp_path)
    assert src.frames == [0, 1, 2] and "obstacles" in src.static
    v = kv.Viewer.for_run(tmp_path, width=320, height=240)
    try:
        assert v.paused and v.frame == 0
        names = {i.name for i in v._items}
        assert names == {"fluid", "obstacles", "surface"}
        assert not v._structures["surface"][1].is_enabled()  # the particles show, the surface on demand
        v.step()
        assert v.frame == 1 and v.time == pytest.approx(1 / scene.fps)
        x1 = next(i for i in v._items if i.name == "fluid").points
        v.seek(2)
        assert v.frame == 2
        assert not np.array_equal(next(i for i in v._items if i.name == "fluid").points, x1)
        v.step()  # wraps round
        assert v.frame == 0
    finally:
        v.close()


def test_without_a_display_one_clear_message(monkeypatch, tmp_path, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the DISPLAY check is Linux's")
    assert "xvfb-run" in kv.display_problem()
    with pytest.raises(kv.ViewerUnavailable, match="no display"):
        kv.Viewer("dam_break", quick=True)
    from kinema.cli import main

    assert main(["run", "dam_break", "--quick", "--view"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("kinema: no display") and "Traceback" not in err
    (tmp_path / "fluid").mkdir()
    assert main(["view", str(tmp_path)]) == 2
    assert "no VTU, PLY or VTI" in capsys.readouterr().err


def test_bad_sources_are_named():
    with pytest.raises(ValueError, match="source"):
        kv._source(42, False, ())
    with pytest.raises(FileNotFoundError, match="no such folder"):
        kv.RunSource("/nonexistent/run")


def test_3d_grid_run_drawn_as_a_volume_with_a_slice(display, tmp_path):
    scene = km.Scene.load(km.scenes.resolve("smoke_plume_3d"), quick=True,
                          overrides=[("output.every", 1), ("output.png", False), ("output.mp4", False)])
    scene.run(tmp_path, 3, progress=False)
    v = kv.Viewer.for_run(tmp_path, width=320, height=240, quantity="density")
    try:
        v.seek(2)
        kind, grid = v._structures["grid"]
        assert kind == "volume_grid"
        img = v.screenshot()
        shape = next(f for f in v._items[0].fields.values() if f.ndim == 3).shape
        corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], float) * shape * v._items[0].h
        col, row = v.project(corners)
        inside = img[int(row.min()) + 3:int(row.max()) - 3, int(col.min()) + 3:int(col.max()) - 3].astype(int)
        background = img[2, 2].astype(int)
        # The slice through the middle of the box shows the density's colours over the box.
        assert (np.abs(inside - background).sum(axis=2) > 30).mean() > 0.3
    finally:
        v.close()


def test_2d_velocity_drawn_as_arrows_on_a_coarse_lattice(display):
    # A solid rotation about the grid's centre: every arrow but the centre's has length.
    from kinema.scenes.adapters.base import GridData

    nx, ny, h = 64, 48, 1.0 / 64
    xc, yc = np.meshgrid((np.arange(nx) + 0.5) * h, (np.arange(ny) + 0.5) * h, indexing="ij")
    velocity = np.stack([-(yc - ny * h / 2), xc - nx * h / 2], axis=-1)
    speed = np.linalg.norm(velocity, axis=-1)
    source = kv.CallbackSource(lambda: 1, lambda: [GridData("grid", {"speed": speed, "velocity": velocity}, h)])
    v = kv.Viewer(source, width=320, height=240)
    try:
        arrows = [k for k in v._structures if k.endswith("arrows")]
        assert arrows == ["grid velocity arrows"], list(v._structures)
        stride = max(nx, ny) // kv.ARROWS_ACROSS
        cloud = v._structures[arrows[0]][1]
        assert cloud.n_points() == len(range(stride // 2, nx, stride)) * len(range(stride // 2, ny, stride))
        with_arrows = v.screenshot().astype(int)
        cloud.set_enabled(False)
        without = v.screenshot().astype(int)
        col, row = v.project(np.array([[0, 0], [nx * h, ny * h]], float))
        c0, c1 = sorted(col.astype(int))
        r0, r1 = sorted(row.astype(int))
        changed = np.abs(with_arrows - without).sum(axis=2) > 30
        # 32 x 24 arrows, the longest a stride (5 pixels here) long: a few per cent of the grid.
        assert changed[r0:r1, c0:c1].mean() > 0.01, changed[r0:r1, c0:c1].mean()
        # Nothing beyond the grid by more than an arrow's length (stride cells) and its head.
        pad = int(2 * stride * (c1 - c0) / nx) + 2
        outside = changed.copy()
        outside[max(r0 - pad, 0):r1 + pad, max(c0 - pad, 0):c1 + pad] = False
        assert not outside.any()
    finally:
        v.close()
