"""Files a scene run writes, each atomically (a temporary file in the same folder, then
os.replace), so an interrupted or killed run never leaves a half-written file under a final name.

* PNG images (8-bit RGB, zlib; no imaging library needed)
* VTK image data (.vti, binary inline) for cell-centred grids; VTU and PLY through meshio
  for particles and meshes
* MP4 video from the PNG frames through ffmpeg
* the ``.npz`` checkpoint from which ``kinema run --resume`` continues
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import struct
import subprocess
import tempfile
import zlib
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def atomic_path(path):
    """Yields a temporary path beside ``path``; on success it replaces ``path``, on any
    exception (KeyboardInterrupt included) it is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


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


def write_vti(path, fields, h, origin=(0.0, 0.0, 0.0)):
    """Cell-centred fields on a grid of cells of size h [m] as VTK XML image data (binary).

    fields: name -> array of the grid's shape (a scalar) or shape + (d,) (a vector, padded to 3
    components). ParaView reads it; :func:`read_vti` reads it back."""
    fields = {name: np.asarray(a, dtype=np.float64) for name, a in fields.items()}
    dims = min((a.shape for a in fields.values()), key=len)  # the grid: a scalar's shape
    arrays = []
    for name, a in fields.items():
        ncomp = 1 if a.shape == dims else a.shape[-1]
        if a.shape[:len(dims)] != dims:
            raise ValueError(f"fields[{name!r}]: expected shape {dims} or {dims} + (d,), got {a.shape}")
        if ncomp > 1:
            a = np.concatenate([a, np.zeros(dims + (3 - ncomp,))], axis=-1) if ncomp < 3 else a
            ncomp = 3
        # VTK runs x fastest; the arrays are [i, j(, k)] with the last index fastest.
        grid = a.reshape(dims + (1,) * (3 - len(dims)) + ((ncomp,) if ncomp > 1 else ()))
        data = np.ascontiguousarray(np.moveaxis(grid, (0, 1, 2), (2, 1, 0))).tobytes()
        payload = base64.b64encode(struct.pack("<Q", len(data)) + data).decode("ascii")
        arrays.append(f'        <DataArray type="Float64" Name="{name}" NumberOfComponents="{ncomp}" '
                      f'format="binary">{payload}</DataArray>\n')
    shape3 = tuple(dims) + (1,) * (3 - len(dims))
    extent = " ".join(f"0 {n}" for n in shape3)
    org = " ".join(str(float(o)) for o in list(origin) + [0.0] * (3 - len(origin)))
    text = ('<?xml version="1.0"?>\n<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" '
            'header_type="UInt64">\n'
            f'  <ImageData WholeExtent="{extent}" Origin="{org}" Spacing="{h} {h} {h}">\n'
            f'    <Piece Extent="{extent}">\n      <CellData>\n' + "".join(arrays)
            + "      </CellData>\n    </Piece>\n  </ImageData>\n</VTKFile>\n")
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def read_vti(path):
    """Reads a file of :func:`write_vti`: (fields as [i, j, k(, c)] arrays, spacing, origin)."""
    import xml.etree.ElementTree as ET

    image = ET.parse(path).getroot().find("ImageData")
    ext = [int(v) for v in image.get("WholeExtent").split()]
    shape = (ext[1] - ext[0], ext[3] - ext[2], ext[5] - ext[4])
    fields = {}
    for arr in image.iter("DataArray"):
        raw = base64.b64decode(arr.text.strip())
        (nbytes,) = struct.unpack("<Q", raw[:8])
        ncomp = int(arr.get("NumberOfComponents", "1"))
        flat = np.frombuffer(raw[8:8 + nbytes], dtype="<f8")
        vtk = flat.reshape(shape[::-1] + ((ncomp,) if ncomp > 1 else ()))
        fields[arr.get("Name")] = np.moveaxis(vtk, (0, 1, 2), (2, 1, 0))
    spacing = [float(v) for v in image.get("Spacing").split()]
    origin = [float(v) for v in image.get("Origin").split()]
    return fields, spacing, origin


def _meshio():
    try:
        import meshio
    except ImportError:
        raise ImportError("VTU and PLY output need meshio: pip install 'kinema[scenes]' "
                          "(scripts/setup.sh installs it)") from None
    return meshio


def write_mesh(path, points, cells=(), point_data=None, file_format=None):
    """Points (with optional cells: [(meshio cell type, (m, k) indices)]) as VTU or PLY via
    meshio; 2D points are padded with z = 0."""
    meshio = _meshio()
    p = np.asarray(points, dtype=np.float64)
    if p.shape[1] == 2:
        p = np.hstack([p, np.zeros((len(p), 1))])
    cells = list(cells) or [("vertex", np.arange(len(p), dtype=np.int64)[:, None])]
    if file_format == "ply" or (file_format is None and str(path).endswith(".ply")):
        # PLY holds polygons only: a point cloud is written without cells.
        cells = [(kind, np.asarray(c, np.int32)) for kind, c in cells if kind in ("triangle", "quad")]
        file_format = "ply"
    else:
        file_format = file_format or "vtu"
    data = {}
    for name, value in (point_data or {}).items():
        value = np.asarray(value, dtype=np.float64)
        if value.ndim == 2 and file_format == "ply":  # PLY properties are scalars: one per component
            data.update({f"{name}_{'xyz'[c]}": np.ascontiguousarray(value[:, c]) for c in range(value.shape[1])})
        else:
            data[name] = np.ascontiguousarray(value)
    with atomic_path(path) as tmp:
        meshio.write_points_cells(str(tmp), p, cells, point_data=data, file_format=file_format,
                                  **({"binary": True} if file_format in ("vtu", "ply") else {}))


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


def load_checkpoint(path):
    """(state, meta) as written by :func:`save_checkpoint`."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        state = {k[len("state/"):]: z[k] for k in z.files if k.startswith("state/")}
    return state, meta
