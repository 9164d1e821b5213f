"""Files a scene run writes besides kinema.io's data files, each atomically (a temporary file
in the same folder, then os.replace, with the umask's permissions), so an interrupted or killed
run never leaves a half-written file under a final name.

* PNG images (8-bit RGB, zlib; no imaging library needed)
* MP4 video from the PNG frames through ffmpeg
* the ``.npz`` checkpoint from which ``kinema run --resume`` continues, read back with every
  kind of damage reported as one :class:`CheckpointError` naming the file
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np

from kinema.io import atomic_path, write_grid

__all__ = ["atomic_path", "write_png", "write_mp4", "save_checkpoint", "load_checkpoint",
           "CheckpointError"]


def write_png(path, rgb):
    """An (H, W, 3) uint8 image as a PNG file (row 0 at the top)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb: expected shape (H, W, 3), got {rgb.shape}")
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, 3 * w)], axis=1)  # filter 0

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))
    with atomic_path(path) as tmp:
        tmp.write_bytes(png)


def write_mp4(path, frame_pattern, fps, start_number=0):
    """Encodes the PNG frames ``frame_pattern`` (printf style, e.g. frames/frame_%05d.png)
    into an H.264 MP4 with ffmpeg. Returns False (writing nothing) when ffmpeg is missing."""
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        return False
    with atomic_path(path) as tmp:
        subprocess.run([ffmpeg, "-y", "-loglevel", "error", "-framerate", f"{fps:g}",
                        "-start_number", str(start_number), "-i", str(frame_pattern),
                        "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p",
                        "-c:v", "libx264", "-f", "mp4", str(tmp)],
                       check=True, stdin=subprocess.DEVNULL)
    return True


def save_checkpoint(path, state, meta):
    """state: name -> array (every evolving quantity); meta: JSON-able dict (frame, config)."""
    arrays = {f"state/{k}": np.asarray(v) for k, v in state.items()}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed from: names the file and what is wrong with it."""


def load_checkpoint(path):
    """(state, meta) as written by :func:`save_checkpoint`. A missing, truncated, empty or
    altered file, or one without the expected entries, raises :class:`CheckpointError`."""
    import zipfile
    import zlib as _zlib

    def bad(what):
        return CheckpointError(f"{path}: damaged checkpoint ({what}); run without --resume to start over")

    try:
        with open(path, "rb") as fh:  # closed whatever np.load makes of the bytes
            z = np.load(fh, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise bad("not an .npz archive")
            with z:
                if "meta" not in z.files:
                    raise bad("no meta entry")
                meta = json.loads(str(z["meta"]))
                state = {k[len("state/"):]: z[k] for k in z.files if k.startswith("state/")}
    except CheckpointError:
        raise
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no checkpoint (run without --resume first)") from None
    except IsADirectoryError:
        raise CheckpointError(f"{path}: is a folder, expected a checkpoint file") from None
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, TypeError, AttributeError,
            _zlib.error, UnicodeDecodeError, RecursionError) as exc:
        raise bad(f"{exc.__class__.__name__}: {str(exc)[:120]}") from None
    if not isinstance(meta, dict):
        raise bad("meta is not a table")
    for key, kind in (("frame", int), ("fingerprint", str)):
        if not isinstance(meta.get(key), kind) or isinstance(meta.get(key), bool):
            raise bad(f"meta.{key} missing or not {'an integer' if kind is int else 'a string'}")
    if meta["frame"] < 0:
        raise bad(f"meta.frame = {meta['frame']} is negative")
    for name, value in state.items():
        if value.dtype.kind not in "biuf":
            raise bad(f"{name} holds {value.dtype}, not numbers")
    return state, meta
