"""Simulations and finished runs inline in Jupyter: ``km.show(...)``.

    km.show(km.render.tone_map(image))        # an (H, W, 3) image
    km.show("out/dam")                        # a finished run: its video, else its last frame
    km.show(scene_or_name, frames=30)         # runs a scene (to a temporary folder) and shows it
    km.show(sim)                              # the current frame of a scene's simulation

The objects returned render themselves in a notebook (``_repr_png_`` for an image,
``_repr_html_`` for a video: an HTML5 <video> with the MP4 inline) and can be saved
(``.save(path)``). Outside Jupyter they are plain objects holding the bytes.
"""

from __future__ import annotations

import base64
import tempfile
import zlib
from pathlib import Path
import struct

import numpy as np

__all__ = ["show", "Image", "Video"]


def png_bytes(rgb):
    """An (H, W, 3) uint8 image as PNG file bytes (no dependency beyond zlib)."""
    rgb = np.ascontiguousarray(rgb, np.uint8)
    h, w, _ = rgb.shape

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    raw = b"".join(b"\x00" + rgb[r].tobytes() for r in range(h))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


class Image:
    """An image that shows itself in Jupyter. pixels: (H, W, 3) uint8."""

    def __init__(self, pixels):
        p = np.asarray(pixels)
        if p.ndim == 2:
            p = np.repeat(p[:, :, None], 3, axis=2)
        if p.ndim != 3 or p.shape[2] not in (3, 4):
            raise ValueError(f"image: expected shape (H, W, 3), got {p.shape}")
        if p.dtype != np.uint8:
            from kinema.render import tone_map

            p = tone_map(p[..., :3])
        self.pixels = np.ascontiguousarray(p[..., :3])

    def _repr_png_(self):
        return png_bytes(self.pixels)

    def save(self, path):
        Path(path).write_bytes(self._repr_png_())
        return Path(path)

    def __repr__(self):
        h, w, _ = self.pixels.shape
        return f"Image({w}x{h})"


class Video:
    """An MP4 that shows itself in Jupyter as an HTML5 video (inline, base64)."""

    def __init__(self, path, *, width=None):
        self.path = Path(path)
        self.width = width
        self.data = self.path.read_bytes()

    def _repr_html_(self):
        b64 = base64.b64encode(self.data).decode()
        width = f' width="{int(self.width)}"' if self.width else ""
        return (f'<video controls loop autoplay muted playsinline{width}>'
                f'<source src="data:video/mp4;base64,{b64}" type="video/mp4"></video>')

    def save(self, path):
        Path(path).write_bytes(self.data)
        return Path(path)

    def __repr__(self):
        return f"Video({self.path}, {len(self.data)} bytes)"


def _run_folder(out):
    out = Path(out)
    video = out / "video.mp4"
    if video.exists():
        return Video(video)
    frames = sorted((out / "frames").glob("frame_*.png"))
    if not frames:
        raise ValueError(f"source: {out} holds neither video.mp4 nor frames/frame_*.png (run with output.png on)")
    from matplotlib import image as mpl_image

    return Image((mpl_image.imread(frames[-1])[..., :3] * 255).round().astype(np.uint8))


def show(source, *, frames=None, quick=False, overrides=(), out=None):
    """Something to display inline: an Image or a Video (see the module docstring).

    source: an (H, W, 3) image array; a run folder; a km.Scene, example name or scene file
    (run for ``frames`` frames, default the scene's whole duration, into ``out`` or a temporary
    folder; ``quick`` and ``overrides`` as in km.Scene.load); or a scene's simulation
    (``scene.build()``), shown at its current state.
    """
    from kinema.scenes.adapters.base import Simulation
    from kinema.scenes.scene import Scene

    if isinstance(source, np.ndarray):
        return Image(source)
    if isinstance(source, Simulation):
        return Image(source.image(source.scene.config["output"]))
    if isinstance(source, (str, Path)) and Path(source).is_dir():
        return _run_folder(source)
    if isinstance(source, (str, Path)):
        from kinema.scenes import resolve

        source = Scene.load(resolve(str(source)), overrides=overrides, quick=quick)
    if not isinstance(source, Scene):
        raise ValueError(f"source: expected an image array, a run folder, a scene or a simulation, got {source!r}")
    folder = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="kinema_show_"))
    source.run(folder, frames, progress=False)
    return _run_folder(folder)
