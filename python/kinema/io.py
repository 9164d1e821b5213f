"""Files for ParaView and Blender: particles, meshes, grids and time series, with no dependency
beyond NumPy.

* :func:`write_particles` -- points with per-point data as VTK XML unstructured grid (``.vtu``)
  or binary PLY (``.ply``); a :class:`kinema.sph.Fluid` is written in its input order (rows
  reordered by ``fluid.ids``), so particle k is row k in every frame.
* :func:`write_mesh` -- triangles or tetrahedra (or any mix of cell types) as ``.vtu``, ``.ply``
  (triangles) or ``.obj`` (triangles).
* :func:`write_grid` -- cell-centred fields as VTK image data (``.vti``).
* :class:`Series` -- a ``.pvd`` (or ParaView ``.series``) file that lists the frames with their
  simulated times, so that ParaView's time axis is the simulation's.
* :func:`read_vtk` -- reads the ``.vtu`` and ``.vti`` files written here back into arrays.

VTK XML arrays are zlib-compressed (``compress=True``, the default) and written binary inline,
so a file is one self-contained document. Every file is written to a temporary name in the
same folder and renamed into place (a killed run leaves no half-written file) with the
permissions the process's umask gives new files.

Example::

    import kinema as km
    series = km.io.Series("out/fluid.pvd")
    for frame in range(100):
        fluid.advance(1 / 30)
        path = f"out/fluid/fluid_{frame:05d}.vtu"
        km.io.write_particles(path, fluid)
        series.add(fluid.time, path)
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import struct
import tempfile
import xml.etree.ElementTree as ET
import zlib
from xml.sax.saxutils import quoteattr
from pathlib import Path

import numpy as np

from kinema._checks import as_float_array, finite, spacing

__all__ = ["write_particles", "write_mesh", "write_grid", "Series", "read_vtk", "atomic_path"]

_BLOCK = 1 << 20  # bytes per compressed block of a VTK array

# VTK cell types by name and vertex count; the names are meshio's.
_VTK_CELLS = {"vertex": (1, 1), "line": (3, 2), "triangle": (5, 3), "quad": (9, 4), "tetra": (10, 4),
              "hexahedron": (12, 8)}
_BY_WIDTH = {1: "vertex", 2: "line", 3: "triangle", 4: "tetra"}


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path):
    """Yields a temporary path beside ``path``; on success it is given the permissions of a
    new file (0666 less the umask) and replaces ``path``; on any exception (KeyboardInterrupt
    included) it is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _parent(path):
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path: expected a file name, got {path!r}")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"path: {path} is a folder, expected a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"path: cannot create the folder {path.parent} ({exc.strerror})") from None
    return path


# ----------------------------------------------------------------------------- VTK XML

_VTK_TYPES = {np.dtype("<f8"): "Float64", np.dtype("<f4"): "Float32", np.dtype("<i8"): "Int64",
              np.dtype("<i4"): "Int32", np.dtype("uint8"): "UInt8"}


def _encode(array, compress):
    """The text of a binary inline VTK DataArray (UInt64 headers), zlib-compressed in blocks."""
    raw = np.ascontiguousarray(array).tobytes()
    if not compress:
        return base64.b64encode(struct.pack("<Q", len(raw)) + raw).decode("ascii")
    blocks = [raw[i:i + _BLOCK] for i in range(0, len(raw), _BLOCK)]
    packed = [zlib.compress(b, 6) for b in blocks]
    last = len(blocks[-1]) if blocks else 0
    header = struct.pack(f"<{3 + len(packed)}Q", len(packed), _BLOCK, last, *(len(p) for p in packed))
    return base64.b64encode(header).decode("ascii") + base64.b64encode(b"".join(packed)).decode("ascii")


def _data_array(name, array, compress, ncomp=None, single=False):
    a = np.asarray(array)
    if a.dtype == bool:
        a = a.astype(np.uint8)
    elif a.dtype.kind == "f":
        a = a.astype("<f4" if single else "<f8")
    elif a.dtype.kind in "iu" and a.dtype != np.uint8:
        a = a.astype("<i8")
    if ncomp is None:
        ncomp = 1 if a.ndim == 1 else a.shape[1]
    comps = f' NumberOfComponents="{ncomp}"' if ncomp > 1 else ""
    return (f'<DataArray type="{_VTK_TYPES[a.dtype]}" Name={quoteattr(str(name))}{comps} '
            f'format="binary">{_encode(a, compress)}</DataArray>')


def _vtk_document(kind, body, compress):
    comp = ' compressor="vtkZLibDataCompressor"' if compress else ""
    return (f'<?xml version="1.0"?>\n<VTKFile type="{kind}" version="1.0" byte_order="LittleEndian" '
            f'header_type="UInt64"{comp}>\n{body}</VTKFile>\n')


def _points3(points, name="points"):
    p = as_float_array(points, name, finite=False)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(f"{name}: expected shape (n, 2) or (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains NaN or inf")
    if p.shape[1] == 2:
        p = np.hstack([p, np.zeros((len(p), 1))])
    return np.ascontiguousarray(p)


def _point_data(data, n, fmt="vtu"):
    out = {}
    if data is not None and not isinstance(data, dict):
        raise ValueError(f"point_data: expected a dict of name -> array, got {type(data).__name__}")
    for name, value in (data or {}).items():
        v = np.asarray(value)
        if v.dtype.kind not in "biuf" or v.dtype == object:
            raise ValueError(f"point_data[{name!r}]: expected numbers, got dtype {v.dtype}")
        if v.ndim == 0 or v.shape[0] != n or v.ndim > 2:
            raise ValueError(f"point_data[{name!r}]: expected shape ({n},) or ({n}, k), got {v.shape}")
        if v.ndim == 2 and v.shape[1] == 2 and fmt == "vtu":  # ParaView shows 3-vectors
            v = np.hstack([v, np.zeros((n, 1), v.dtype)])
        out[str(name)] = v
    return out


def _cells(cells, npoints):
    """[(type name, (m, k) int array)] from an (m, k) array, a dict or a list of pairs."""
    if cells is None:
        return []
    if isinstance(cells, dict):
        items = list(cells.items())
    elif isinstance(cells, np.ndarray) or (isinstance(cells, (list, tuple)) and cells and not isinstance(cells[0], tuple)):
        c = np.asarray(cells)
        if c.ndim != 2 or c.shape[1] not in _BY_WIDTH:
            raise ValueError(f"cells: expected an (m, 3) triangle or (m, 4) tetrahedron array, got shape {c.shape}")
        items = [(_BY_WIDTH[c.shape[1]], c)]
    else:
        items = list(cells)
    out = []
    for kind, c in items:
        if kind not in _VTK_CELLS:
            raise ValueError(f"cells: unknown cell type {kind!r} (known: {', '.join(_VTK_CELLS)})")
        c = np.asarray(c)
        width = _VTK_CELLS[kind][1]
        if c.size == 0:
            continue
        if c.dtype.kind not in "iu" or c.ndim != 2 or c.shape[1] != width:
            raise ValueError(f"cells[{kind!r}]: expected an integer array of shape (m, {width}), got "
                             f"{c.dtype} {c.shape}")
        if c.min() < 0 or c.max() >= npoints:
            raise ValueError(f"cells[{kind!r}]: vertex indices must lie in [0, {npoints}), got "
                             f"[{c.min()}, {c.max()}]")
        out.append((kind, c.astype(np.int64)))
    return out


def _write_vtu(path, points, cells, point_data, cell_data, compress):
    n = len(points)
    if not cells:
        cells = [("vertex", np.arange(n, dtype=np.int64)[:, None])]
    conn = np.concatenate([c.ravel() for _, c in cells])
    offsets = np.cumsum(np.concatenate([np.full(len(c), c.shape[1], np.int64) for _, c in cells]))
    types = np.concatenate([np.full(len(c), _VTK_CELLS[k][0], np.uint8) for k, c in cells])
    m = len(types)
    cdata = {}
    for name, value in (cell_data or {}).items():
        v = np.asarray(value)
        if v.ndim == 0 or v.shape[0] != m:
            raise ValueError(f"cell_data[{name!r}]: expected {m} values (one per cell), got shape {v.shape}")
        cdata[name] = v
    pd = "".join(f"        {_data_array(k, v, compress)}\n" for k, v in point_data.items())
    cd = "".join(f"        {_data_array(k, v, compress)}\n" for k, v in cdata.items())
    body = (f'  <UnstructuredGrid>\n    <Piece NumberOfPoints="{n}" NumberOfCells="{m}">\n'
            f'      <PointData>\n{pd}      </PointData>\n      <CellData>\n{cd}      </CellData>\n'
            f'      <Points>\n        {_data_array("Points", points, compress, 3)}\n      </Points>\n'
            f'      <Cells>\n        {_data_array("connectivity", conn, compress, 1)}\n'
            f'        {_data_array("offsets", offsets, compress, 1)}\n'
            f'        {_data_array("types", types, compress, 1)}\n      </Cells>\n'
            f'    </Piece>\n  </UnstructuredGrid>\n')
    with atomic_path(path) as tmp:
        tmp.write_text(_vtk_document("UnstructuredGrid", body, compress))


def _write_ply(path, points, triangles, point_data):
    """Binary little-endian PLY: vertices with their scalar properties (a k-vector becomes k
    properties name_x, name_y, ...) and triangle faces."""
    props = [("x", points[:, 0]), ("y", points[:, 1]), ("z", points[:, 2])]
    for name, v in point_data.items():
        v = np.asarray(v, dtype=np.float64)
        if v.ndim == 1:
            props.append((name, v))
        else:
            props += [(f"{name}_{'xyzw'[c] if v.shape[1] <= 4 else c}", v[:, c]) for c in range(v.shape[1])]
    n = len(points)
    vert = np.empty(n, dtype=[(name, "<f8") for name, _ in props])
    for name, v in props:
        vert[name] = v
    tri = np.asarray(triangles if triangles is not None else np.zeros((0, 3)), dtype=np.int64)
    face = np.empty(len(tri), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = tri
    header = ["ply", "format binary_little_endian 1.0", "comment written by kinema.io", f"element vertex {n}"]
    header += [f"property double {name}" for name, _ in props]
    if len(tri):
        header += [f"element face {len(tri)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vert.tobytes())
            if len(tri):
                fh.write(face.tobytes())


def _write_obj(path, points, triangles):
    lines = ["# written by kinema.io"]
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in points]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in (triangles if triangles is not None else [])]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def _format(path, known):
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path: expected a file name, got {path!r}")
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in known:
        raise ValueError(f"path: expected a file name ending in {', '.join('.' + k for k in known)}, got {str(path)!r}")
    return suffix


def write_particles(path, points, point_data=None, *, ids=None, compress=True):
    """Writes particles to ``path`` (``.vtu`` or ``.ply``, chosen by the suffix) and returns it.

    points: an (n, 2) or (n, 3) array (2D points get z = 0), or a :class:`kinema.sph.Fluid`,
    whose positions, velocities, densities and pressures are written with their ``id``.
    point_data: name -> (n,) or (n, k) array. ids: the input index of each row (as
    ``fluid.ids``): rows are reordered so that the file's row k is particle k, a stable order
    across frames whatever the solver's reordering. compress: zlib-compress VTU arrays.
    """
    if hasattr(points, "ids") and hasattr(points, "x"):
        fluid = points
        points, ids = fluid.x, fluid.ids
        data = {"velocity": fluid.v, "density": fluid.density, "pressure": fluid.pressure}
        data.update(point_data or {})
        point_data = data
    fmt = _format(path, ("vtu", "ply"))
    p = _points3(points)
    data = _point_data(point_data, len(p), fmt)
    if ids is not None:
        ids = np.asarray(ids)
        if ids.shape != (len(p),) or ids.dtype.kind not in "iu":
            raise ValueError(f"ids: expected {len(p)} integers, got {ids.dtype} {ids.shape}")
        if not np.array_equal(np.sort(ids), np.arange(len(p))):
            raise ValueError("ids: expected a permutation of 0..n-1")
        order = np.empty(len(p), dtype=np.int64)
        order[ids] = np.arange(len(p))
        p = p[order]
        data = {k: v[order] for k, v in data.items()}
        data["id"] = np.arange(len(p), dtype=np.int64) if fmt == "vtu" else np.arange(len(p), dtype=float)
    path = _parent(path)
    if fmt == "ply":
        _write_ply(path, p, None, data)
    else:
        _write_vtu(path, p, [], data, None, compress)
    return path


def write_mesh(path, points, cells, point_data=None, cell_data=None, *, compress=True):
    """Writes a mesh to ``path`` (``.vtu``, ``.ply`` or ``.obj``, by the suffix) and returns it.

    cells: an (m, 3) triangle or (m, 4) tetrahedron index array, or ``{type: array}`` /
    ``[(type, array)]`` with meshio's type names (vertex, line, triangle, quad, tetra,
    hexahedron). PLY and OBJ hold the triangles only (pass a tet mesh's surface triangles);
    cell_data (one value per cell, in the order given) is VTU only.
    """
    fmt = _format(path, ("vtu", "ply", "obj"))
    p = _points3(points)
    c = _cells(cells, len(p))
    data = _point_data(point_data, len(p), fmt)
    path = _parent(path)
    if fmt == "vtu":
        _write_vtu(path, p, c, data, cell_data, compress)
        return path
    other = [k for k, _ in c if k != "triangle"]
    if other or cell_data:
        raise ValueError(f"cells: a .{fmt} file holds triangles only, got {', '.join(other) or 'cell_data'} "
                         "(write .vtu, or pass the surface triangles)")
    tri = next((a for k, a in c if k == "triangle"), None)
    if fmt == "ply":
        _write_ply(path, p, tri, data)
    else:
        _write_obj(path, p, tri)
    return path


def write_grid(path, fields, h, origin=(0.0, 0.0, 0.0), *, compress=True, single=False):
    """Cell-centred fields on cells of size ``h`` [m] as VTK image data (``.vti``); returns the path.

    fields: name -> array of the grid's shape (a scalar, e.g. ``fluid.density``) or the grid's
    shape + (d,) (a vector, padded to 3 components). origin: the lower corner of cell (0, 0, 0).
    single: store the values as float32 (half the size, 7 significant digits; enough to look
    at, not to restart from). Read back with :func:`read_vtk`.
    """
    _format(path, ("vti",))
    if not fields:
        raise ValueError("fields: expected at least one field")
    if not isinstance(fields, dict):
        raise ValueError(f"fields: expected a dict of name -> array, got {type(fields).__name__}")
    h = spacing(h, "h")
    fields = {name: as_float_array(a, f"fields[{name!r}]") for name, a in fields.items()}
    dims = min((a.shape for a in fields.values()), key=len)  # the grid: a scalar's shape
    if len(dims) not in (2, 3):
        raise ValueError(f"fields: expected 2D or 3D grids, got shape {dims}")
    arrays = []
    for name, a in fields.items():
        if a.shape[:len(dims)] != dims or a.ndim > len(dims) + 1:
            raise ValueError(f"fields[{name!r}]: expected shape {dims} or {dims} + (d,), got {a.shape}")
        ncomp = 1 if a.shape == dims else a.shape[-1]
        if ncomp > 1:
            if ncomp < 3:
                a = np.concatenate([a, np.zeros(dims + (3 - ncomp,))], axis=-1)
            ncomp = a.shape[-1]
        # VTK runs x fastest; the arrays are [i, j(, k)] with the last index fastest.
        grid = a.reshape(dims + (1,) * (3 - len(dims)) + ((ncomp,) if ncomp > 1 else ()))
        data = np.moveaxis(grid, (0, 1, 2), (2, 1, 0)).reshape(-1, ncomp) if ncomp > 1 else \
            np.moveaxis(grid, (0, 1, 2), (2, 1, 0)).ravel()
        arrays.append(f"        {_data_array(name, data, compress, ncomp, single)}\n")
    shape3 = tuple(dims) + (1,) * (3 - len(dims))
    extent = " ".join(f"0 {n}" for n in shape3)
    origin = as_float_array(origin, "origin", ndim=1)
    if not 2 <= origin.size <= 3:
        raise ValueError(f"origin: expected 2 or 3 coordinates, got {origin.size}")
    org = " ".join(repr(float(o)) for o in (list(origin) + [0.0] * 3)[:3])
    body = (f'  <ImageData WholeExtent="{extent}" Origin="{org}" Spacing="{h!r} {h!r} {h!r}">\n'
            f'    <Piece Extent="{extent}">\n      <CellData>\n' + "".join(arrays)
            + "      </CellData>\n    </Piece>\n  </ImageData>\n")
    path = _parent(path)
    with atomic_path(path) as tmp:
        tmp.write_text(_vtk_document("ImageData", body, compress))
    return path


def _decode(text, dtype, compressed):
    text = text.strip()
    if not compressed:
        raw = base64.b64decode(text)
        (nbytes,) = struct.unpack("<Q", raw[:8])
        return np.frombuffer(raw[8:8 + nbytes], dtype=dtype)
    # The header (3 + blocks UInt64) is encoded on its own: its base64 length is known.
    (nblocks,) = struct.unpack("<Q", base64.b64decode(text[:12])[:8])
    hlen = 4 * ((8 * (3 + nblocks) + 2) // 3)
    header = struct.unpack(f"<{3 + nblocks}Q", base64.b64decode(text[:hlen]))
    payload = base64.b64decode(text[hlen:])
    out, pos = [], 0
    for size in header[3:]:
        out.append(zlib.decompress(payload[pos:pos + size]))
        pos += size
    return np.frombuffer(b"".join(out), dtype=dtype)


def read_vtk(path):
    """Reads a ``.vti`` or ``.vtu`` file of this module into a dict.

    ``.vti``: {"fields": name -> [i, j, k(, c)] array, "spacing", "origin"}; ``.vtu``:
    {"points", "cells": [(type, array)], "point_data", "cell_data"}.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path: expected a file name, got {path!r}")
    try:
        return _read_vtk(path)
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (ET.ParseError, zlib.error, AttributeError, KeyError, TypeError, IndexError,
            struct.error, ValueError) as exc:
        raise ValueError(f"{path}: not a readable VTK file written by kinema.io "
                         f"({type(exc).__name__}: {exc})") from None


def _read_vtk(path):
    root = ET.parse(path).getroot()
    compressed = root.get("compressor") is not None
    types = {v: k for k, v in _VTK_TYPES.items()}

    def array(node):
        a = _decode(node.text or "", types[node.get("type")], compressed)
        ncomp = int(node.get("NumberOfComponents", "1"))
        return a.reshape(-1, ncomp) if ncomp > 1 else a

    if root.get("type") == "ImageData":
        image = root.find("ImageData")
        ext = [int(v) for v in image.get("WholeExtent").split()]
        shape = (ext[1] - ext[0], ext[3] - ext[2], ext[5] - ext[4])
        fields = {}
        for node in image.iter("DataArray"):
            a = array(node)
            vtk = a.reshape(shape[::-1] + a.shape[1:])
            fields[node.get("Name")] = np.moveaxis(vtk, (0, 1, 2), (2, 1, 0))
        return {"fields": fields, "spacing": [float(v) for v in image.get("Spacing").split()],
                "origin": [float(v) for v in image.get("Origin").split()]}
    piece = root.find("UnstructuredGrid/Piece")
    points = array(piece.find("Points/DataArray"))
    cells_node = {n.get("Name"): array(n) for n in piece.find("Cells").iter("DataArray")}
    names = {code: name for name, (code, _) in _VTK_CELLS.items()}
    cells, start = [], 0
    for code, end in zip(cells_node["types"], cells_node["offsets"]):
        kind = names[int(code)]
        row = cells_node["connectivity"][start:end]
        if cells and cells[-1][0] == kind:
            cells[-1][1].append(row)
        else:
            cells.append((kind, [row]))
        start = end
    return {"points": points, "cells": [(k, np.array(rows)) for k, rows in cells],
            "point_data": {n.get("Name"): array(n) for n in piece.find("PointData").iter("DataArray")},
            "cell_data": {n.get("Name"): array(n) for n in piece.find("CellData").iter("DataArray")}}


class Series:
    """A time series for ParaView: a ``.pvd`` collection (or a ``.series`` JSON file) listing
    data files with their simulated times, rewritten (atomically) at every :meth:`add`.

    ``Series(path)`` starts empty; ``Series(path, resume=True)`` keeps the entries of an
    existing file (for a run that continues). File names are stored relative to the series
    file's folder, so the folder can be moved.
    """

    def __init__(self, path, *, resume=False):
        self.path = Path(path)
        self.format = _format(self.path, ("pvd", "series"))
        self.entries = []  # (time, file name relative to the series' folder)
        if resume and self.path.exists():
            self.entries = self._read()

    def _read(self):
        try:
            if self.format == "series":
                doc = json.loads(self.path.read_text())
                return [(float(e["time"]), e["name"]) for e in doc["files"]]
            root = ET.parse(self.path).getroot()
            return [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]
        except (ValueError, KeyError, TypeError, ET.ParseError) as exc:
            raise ValueError(f"{self.path}: not a readable {self.format} file ({exc})") from None

    def add(self, time, file):
        """Lists ``file`` at simulated time ``time`` [s] (an entry for the same file or a later
        time is replaced: a resumed run overwrites what followed its checkpoint)."""
        time = finite(time, "time")
        if not isinstance(file, (str, os.PathLike)):
            raise ValueError(f"file: expected a file name, got {file!r}")
        rel = os.path.relpath(Path(file), self.path.parent).replace(os.sep, "/")
        self.entries = [(t, f) for t, f in self.entries if f != rel and t < time]
        self.entries.append((time, rel))
        self.write()

    def truncate(self, time):
        """Drops the entries at or after ``time`` (a run resumed from an earlier checkpoint)."""
        self.entries = [(t, f) for t, f in self.entries if t < time]

    def write(self):
        _parent(self.path)
        if self.format == "series":
            text = json.dumps({"file-series-version": "1.0",
                               "files": [{"name": f, "time": t} for t, f in self.entries]}, indent=1)
        else:
            rows = "".join(f'    <DataSet timestep="{t!r}" part="0" file={quoteattr(f)}/>\n' for t, f in self.entries)
            text = ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
                    f"  <Collection>\n{rows}  </Collection>\n</VTKFile>\n")
        with atomic_path(self.path) as tmp:
            tmp.write_text(text)
