"""Free surfaces of particle liquids (SPH, MPM, any particles on a spacing) as triangle meshes.

    mesh = km.surface.reconstruct(fluid.x, spacing)             # marching cubes (default)
    mesh = km.surface.reconstruct(x, spacing, method="splashsurf")
    mesh.write("surface_00010.ply")                               # or .obj
    scene.add_mesh(mesh.vertices, mesh.triangles, km.render.dielectric(1.33))

Two methods (``pip install kinema[surface]``; measured side by side in bench/render/surface_bench.py):

* ``"splashsurf"``: the SPlisHSPlasH group's reconstruction (Löschner, Böttcher, Jeske, Bender,
  "Weighted Laplacian smoothing for surface reconstruction of particle-based fluids", VMV 2023)
  through ``pysplashsurf``: the SPH colour field with the cubic spline kernel of smoothing length
  ``spacing`` (support 2 spacing), marching cubes on a sparse subdomain grid (Rust, threaded).
* ``"marching_cubes"``: each particle's volume spacing^3 deposited on a grid of ``cell``
  (cloud-in-cell), smoothed by a Gaussian of standard deviation ``smoothing`` (the liquid's
  volume fraction, 1 inside, 1/2 at a flat free surface exactly half a spacing beyond the last
  layer of particles, so that the enclosed volume is the particles' volume), and the 1/2 level set
  taken by scikit-image's marching cubes (Lewiner et al. 2003; closed, consistently oriented).

Both give a closed mesh (Euler characteristic 2 per blob without handles) oriented outwards,
in a canonical order (sorted vertices and triangles). marching_cubes is bitwise reproducible;
splashsurf's threaded sums may differ in the last bits from run to run (use marching_cubes
where frames must be identical, e.g. a resumed scene run).
Units: those of the points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinema._checks import as_float_array, finite, positive
from kinema._checks import spacing as _spacing

__all__ = ["Mesh", "reconstruct", "METHODS"]

METHODS = ("marching_cubes", "splashsurf")


@dataclass
class Mesh:
    """A triangle mesh: vertices (m, 3) [length], triangles (k, 3) vertex indices, outward."""

    vertices: np.ndarray
    triangles: np.ndarray

    def edges(self):
        """(e, 2) unique undirected edges and how many triangles share each."""
        t = self.triangles
        e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
        return np.unique(e, axis=0, return_counts=True)

    def euler_characteristic(self) -> int:
        """V - E + F (2 for a closed surface of genus 0; vertices used by a triangle only)."""
        edges, _ = self.edges()
        used = np.unique(self.triangles).size
        return int(used - len(edges) + len(self.triangles))

    def is_closed(self) -> bool:
        """Watertight and consistently oriented: every edge is used by exactly two triangles,
        once in each direction."""
        if len(self.triangles) == 0:
            return False
        _, counts = self.edges()
        if not np.all(counts == 2):
            return False
        t = self.triangles
        directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        return len(np.unique(directed, axis=0)) == len(directed)

    def volume(self) -> float:
        """Enclosed volume (divergence theorem; positive for an outward mesh)."""
        v, t = self.vertices, self.triangles
        return float(np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6)

    def area(self) -> float:
        v, t = self.vertices, self.triangles
        return float(0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum())

    def write(self, path):
        """Writes a PLY (binary) or OBJ file, by the suffix of ``path``; returns the path."""
        path = Path(path)
        v = np.asarray(self.vertices, "<f4")
        t = np.asarray(self.triangles, "<i4")
        if path.suffix == ".obj":
            with open(path, "w") as fh:
                np.savetxt(fh, v, fmt="v %.7g %.7g %.7g")
                np.savetxt(fh, t + 1, fmt="f %d %d %d")
        elif path.suffix == ".ply":
            header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
                      "property float x\nproperty float y\nproperty float z\n"
                      f"element face {len(t)}\nproperty list uchar int vertex_indices\nend_header\n")
            faces = np.empty(len(t), dtype=[("n", "u1"), ("i", "<i4", 3)])
            faces["n"], faces["i"] = 3, t
            with open(path, "wb") as fh:
                fh.write(header.encode())
                fh.write(v.tobytes())
                fh.write(faces.tobytes())
        else:
            raise ValueError(f"path: expected a .ply or .obj file name, got {path.name!r}")
        return path


def _outward(vertices, triangles):
    """The mesh oriented outwards, in a canonical order (vertices sorted by coordinates,
    triangles starting at their smallest index, sorted): the same surface gives the same
    arrays whatever order a threaded reconstruction emitted them in."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    order = np.lexsort(v.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    v, t = v[order], rank[t]
    first = np.argmin(t, axis=1)
    t = np.take_along_axis(t, (first[:, None] + np.arange(3)) % 3, axis=1)  # rotations keep orientation
    t = t[np.lexsort(t.T[::-1])]
    mesh = Mesh(np.ascontiguousarray(v), np.ascontiguousarray(t))
    if len(mesh.triangles) and mesh.volume() < 0:
        mesh.triangles = np.ascontiguousarray(mesh.triangles[:, [0, 2, 1]])
    return mesh


def reconstruct(points, spacing, *, method="marching_cubes", cell=None, iso=None, smoothing=None) -> Mesh:
    """The free surface of the liquid whose particles sit at ``points`` (n, 3), ``spacing``
    apart at rest (each stands for a volume spacing^3).

    method: "marching_cubes" (default: here faster at 150k particles, closer to the sphere in
    the tests, and bitwise reproducible; bench/RESULTS.md) or "splashsurf".
    cell: marching-cubes cell size (default spacing / 2; finer is smoother and slower).
    iso: level of the field taken as the surface (default 0.6 of the rest colour field for
    splashsurf, its own default; 0.5 of the volume fraction for marching_cubes).
    smoothing: marching_cubes' Gaussian standard deviation (default 0.6 spacing: removes the
    lattice's ripple, rounds corners by about a spacing).
    """
    x = as_float_array(points, "points", ndim=2)
    if x.shape[1] != 3:
        raise ValueError(f"points: expected shape (n, 3) (surfaces are 3D), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("points: contains NaN or inf")
    s = _spacing(spacing, "spacing")
    c = _spacing(cell, "cell") if cell is not None else 0.5 * s
    iso = None if iso is None else finite(iso, "iso")
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if len(x) == 0:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    sigma = positive(smoothing, "smoothing") if smoothing is not None else 0.6 * s
    extent = (np.ptp(x, axis=0) + 2 * (3.0 * sigma + s + 2 * c)) / c + 2
    if not np.isfinite(extent).all() or np.prod(extent) > MAX_CELLS:
        raise ValueError(f"points, spacing, cell: the grid around the points would have more than "
                         f"{MAX_CELLS:.0e} cells; use a larger cell or split far-apart particles")
    try:
        if method == "splashsurf":
            return _splashsurf(x, s, c, 0.6 if iso is None else iso)
        return _marching_cubes(x, s, c, 0.5 if iso is None else iso, sigma)
    except RuntimeError as exc:  # "no surface found at the given iso value" and the like
        raise ValueError(f"iso: {exc}") from None


# Largest marching-cubes grid (cells) accepted: 8 GB of float64.
MAX_CELLS = 10**9


def _splashsurf(x, s, c, iso):
    try:
        import pysplashsurf
    except ImportError:
        raise ImportError("method='splashsurf' needs pysplashsurf: pip install 'kinema[surface]'") from None
    r = 0.5 * s  # splashsurf's particle radius: volume (2 r)^3 = s^3
    mesh, _ = pysplashsurf.reconstruction_pipeline(
        x, particle_radius=r, rest_density=1000.0, smoothing_length=s / r, cube_size=c / r,
        iso_surface_threshold=iso, subdomain_grid=True)
    tri = mesh.mesh
    return _outward(np.asarray(tri.vertices), np.asarray(tri.triangles))


def volume_fraction(x, s, c, sigma):
    """The smoothed volume fraction on a grid of cell ``c`` around the points: (field,
    origin of cell (0, 0, 0)'s centre)."""
    pad = 3.0 * sigma + s + 2 * c
    lo = x.min(0) - pad
    shape = np.ceil((x.max(0) + pad - lo) / c).astype(np.int64) + 1
    # Cloud-in-cell: each particle's volume to the 8 cell centres around it.
    g = (x - lo) / c
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    field = np.zeros(int(np.prod(shape)))
    weight = (s / c) ** 3
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1 - f[:, 0]
        for dy in (0, 1):
            wy = wx * (f[:, 1] if dy else 1 - f[:, 1])
            for dz in (0, 1):
                w = wy * (f[:, 2] if dz else 1 - f[:, 2])
                idx = ((i0[:, 0] + dx) * shape[1] + i0[:, 1] + dy) * shape[2] + i0[:, 2] + dz
                field += np.bincount(idx, w, minlength=field.size)
    field = field.reshape(shape) * weight
    return _gaussian(field, sigma / c), lo


def _gaussian(field, sd):
    """scipy's gaussian_filter(field, sd, mode="constant", truncate=3.0), bit for bit, one
    axis at a time in slabs of about a million cells: scipy's C loop does not look for Ctrl-C,
    and a wide filter on a large grid runs for minutes, so each slab is one short call."""
    from scipy.ndimage import gaussian_filter1d

    if sd <= 1e-15:  # gaussian_filter leaves such axes alone
        return field
    for axis in range(field.ndim):
        across = 1 if axis == 0 else 0  # slabs are cut across another axis
        rows = max(1, 2**20 * field.shape[across] // field.size)
        out = np.empty_like(field)
        for k in range(0, field.shape[across], rows):
            part = (slice(None),) * across + (slice(k, k + rows),)
            out[part] = gaussian_filter1d(field[part], sd, axis=axis, mode="constant", truncate=3.0)
        field = out
    return field


def _marching_cubes(x, s, c, iso, sigma):
    try:
        from skimage.measure import marching_cubes
    except ImportError:
        raise ImportError("method='marching_cubes' needs scikit-image: pip install 'kinema[surface]'") from None
    field, lo = volume_fraction(x, s, c, sigma)
    top = float(field.max())
    if not 0.0 < iso < top:
        raise ValueError(f"iso: {iso:g} is outside the smoothed volume fraction's range (0, {top:.3g}), so there is "
                         f"no surface (smoothing = {sigma:.3g} m: a smoothing wide against the liquid spreads it thin)")
    verts, faces = _level_set(field, iso, marching_cubes)
    return _outward(verts * c + lo, faces)


def _level_set(field, iso, marching_cubes, cells=2**20):
    """scikit-image's ``marching_cubes(field, iso)`` (vertices in cell units, float64), run over
    slabs of about ``cells`` cells along axis 0 that share their boundary planes: its C loop does
    not look for Ctrl-C, and on a large grid it runs for a minute, so each slab is one short
    call. Every cube lies in one slab, so the slabs' triangles are the whole call's; a vertex on a
    shared plane lies on an edge of that plane and both slabs interpolate it from the same two
    values to the same numbers, so it is merged by value with the slab before's. The result is
    the whole call's mesh, its coordinates within float32 rounding (scikit-image's precision) of
    the whole call's: a slab rounds its vertices at their index in the slab, not in the grid."""
    n0 = field.shape[0]
    layers = max(1, cells // max(1, field[0].size))
    verts, faces, count = [], [], 0
    seam = None  # the slab before's vertices on its last plane: sorted (y, z) keys, indices
    key = np.dtype((np.void, 8))  # a vertex's float32 (y, z) as one comparable value
    for k0 in range(0, n0 - 1, layers):
        k1 = min(k0 + layers, n0 - 1)
        part = np.ascontiguousarray(field[k0:k1 + 1], np.float32)  # what scikit-image reads and checks
        if not part.min() <= iso <= part.max():
            seam = None
            continue
        try:
            v, f, _, _ = marching_cubes(part, iso, allow_degenerate=False)
        except RuntimeError:  # no vertex in this slab
            seam = None
            continue
        index = np.full(len(v), -1, np.int64)
        if seam is not None:
            first = np.flatnonzero(v[:, 0] == 0)
            keys = np.ascontiguousarray(v[first, 1:]).view(key).ravel()
            at = np.minimum(np.searchsorted(seam[0], keys), len(seam[0]) - 1) if len(seam[0]) else None
            if at is not None:
                hit = seam[0][at] == keys
                index[first[hit]] = seam[1][at[hit]]
        new = index < 0
        index[new] = count + np.arange(np.count_nonzero(new))
        last = np.flatnonzero((v[:, 0] == k1 - k0) & new)
        keys = np.ascontiguousarray(v[last, 1:]).view(key).ravel()
        order = np.argsort(keys, kind="stable")
        seam = (keys[order], index[last][order])
        kept = v[new].astype(np.float64)
        kept[:, 0] += k0
        verts.append(kept)
        faces.append(index[f])
        count += len(kept)
    if not verts:
        raise RuntimeError("No surface found at the given iso value.")
    return np.concatenate(verts), np.concatenate(faces)
