"""Simplex meshes from elsewhere (TetGen, gmsh, scipy's Delaunay, hand-made): orientation, slivers
and boundary surfaces, for :class:`kinema.fem.Body` and for drawing and export.

A mesh is ``vertices`` (n, d) with d = 2 or 3 and ``elements`` (m, d + 1) vertex indices:
triangles in 2D, tetrahedra in 3D. An element is positively oriented when its signed volume

    V = det[x1 - x0, ..., xd - x0] / d!

is positive (counter-clockwise triangles; tetrahedra whose fourth vertex lies on the side of
the face (x0, x1, x2) its right-hand normal points to), as :class:`kinema.fem.Body` requires.

Every function that changes a mesh returns what it changed, so nothing is silently altered::

    verts, tets, report = km.mesh.clean(verts, tets)
    print(report)            # "3 element(s) re-oriented [4, 17, 90]; 2 sliver(s) removed [...]"
    faces = km.mesh.surface(verts, tets)            # (F, 3) outward triangles

Element quality (used to find slivers) is the volume relative to that of the regular simplex
with the element's longest edge L: q = V / (L^3 / (6 sqrt 2)) for a tetrahedron and
q = V / (sqrt(3) L^2 / 4) for a triangle; q = 1 for a regular element, 0 for a flat one. A
Delaunay mesh of points on a lattice holds exactly flat "slivers" (four co-spherical, coplanar
points, q = 0); :class:`kinema.fem.Body` refuses elements with q below about 1e-11.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import factorial, sqrt

import numpy as np

from kinema._checks import as_float_array, real, representable

__all__ = ["MeshReport", "signed_volumes", "quality", "orient", "remove_slivers", "clean", "surface",
           "surface_area", "euler_characteristic", "boundary_edges"]

#: Default quality below which :func:`remove_slivers` drops an element.
SLIVER_QUALITY = 1e-6

# Faces of a positively oriented tetrahedron (a, b, c, d), each with its outward normal by the
# right-hand rule: (b, c, d) opposite a, (a, d, c) opposite b, (a, b, d) opposite c, (a, c, b)
# opposite d. Edges of a counter-clockwise triangle, interior on their left.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_TRI_EDGES = np.array([[0, 1], [1, 2], [2, 0]])


@dataclass
class MeshReport:
    """What :func:`clean` (or :func:`orient`, :func:`remove_slivers`) changed.

    flipped: indices (into the input elements) of the elements re-oriented;
    slivers: indices (into the input elements) of the elements removed as slivers;
    interior_slivers: how many of those had all their faces shared with other elements (their
        removal leaves the neighbours meeting along a flat region with different diagonals, which
        are conforming at the vertices and edges, not across the face);
    unused_vertices: indices (into the input vertices) of vertices no element uses any more,
        removed when ``clean(..., drop_unused=True)``; vertex_map: old index -> new index
        (-1 for a removed vertex), or None when the vertices were kept.
    """

    flipped: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    slivers: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    interior_slivers: int = 0
    unused_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_map: np.ndarray | None = None

    @property
    def changed(self) -> bool:
        return bool(self.flipped.size or self.slivers.size or self.unused_vertices.size)

    def __str__(self) -> str:
        def listing(a):
            a = [int(i) for i in a]
            return str(a) if len(a) <= 10 else f"[{', '.join(map(str, a[:10]))}, ...]"

        parts = []
        if self.flipped.size:
            parts.append(f"{self.flipped.size} element(s) re-oriented {listing(self.flipped)}")
        if self.slivers.size:
            parts.append(f"{self.slivers.size} sliver(s) removed {listing(self.slivers)}"
                         + (f" ({self.interior_slivers} interior)" if self.interior_slivers else ""))
        if self.unused_vertices.size:
            parts.append(f"{self.unused_vertices.size} unused vertex(es) removed")
        return "; ".join(parts) if parts else "mesh unchanged"


def _mesh(vertices, elements, *, name="elements"):
    v = as_float_array(vertices, "vertices", ndim=2)
    n, d = v.shape
    if d not in (2, 3):
        raise ValueError(f"vertices: expected shape (n, 2) or (n, 3), got {v.shape}")
    try:
        e = np.asarray(elements)
        if e.dtype.kind == "f":
            if not np.array_equal(e, np.round(e)):
                raise ValueError
        elif e.dtype.kind not in "iu":
            raise ValueError
        e = np.ascontiguousarray(e, dtype=np.int64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected an array of integer vertex indices") from None
    if e.ndim != 2 or e.shape[1] != d + 1:
        raise ValueError(f"{name}: expected shape (m, {d + 1}) for {d}D vertices, got {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= n):
        raise ValueError(f"{name}: vertex indices must lie in [0, {n}), got [{e.min()}, {e.max()}]")
    if e.size and (np.sort(e, axis=1)[:, 1:] == np.sort(e, axis=1)[:, :-1]).any():
        bad = int(np.flatnonzero((np.sort(e, axis=1)[:, 1:] == np.sort(e, axis=1)[:, :-1]).any(1))[0])
        raise ValueError(f"{name}: element {bad} repeats a vertex ({e[bad].tolist()})")
    return v, e


def signed_volumes(vertices, elements) -> np.ndarray:
    """(m,) signed volumes (3D) or areas (2D) of the elements [m^d]; positive = positively oriented."""
    v, e = _mesh(vertices, elements)
    return representable(_signed(v, e), "vertices", "an element's volume")


def _scaled(v, e):
    """(signed volume, longest edge) of each element with its edges divided by scale, and
    scale: the edge matrix scaled to O(1) entries, so that denormal or huge coordinates neither
    divide by zero inside the LU nor overflow; orientation and quality need no more."""
    d = v.shape[1]
    D = np.stack([v[e[:, a + 1]] - v[e[:, 0]] for a in range(d)], -1)
    scale = np.abs(D).max(axis=(1, 2))
    scale = np.where(scale > 0, scale, 1.0)
    D = D / scale[:, None, None]
    edges = [D[:, :, a] for a in range(d)] + [D[:, :, b] - D[:, :, a] for a in range(d) for b in range(a + 1, d)]
    longest = np.max([np.linalg.norm(x, axis=1) for x in edges], axis=0)
    return np.linalg.det(D) / factorial(d), longest, scale


def _signed(v, e):
    if not len(e):
        return np.zeros(0)
    vol, _, scale = _scaled(v, e)
    with np.errstate(over="ignore", under="ignore"):
        return vol * scale ** v.shape[1]


def quality(vertices, elements) -> np.ndarray:
    """(m,) element quality |V| / V_regular(longest edge) in [0, 1] (see the module docstring);
    0 for an element whose vertices coincide."""
    v, e = _mesh(vertices, elements)
    return _quality(v, e)


def _quality(v, e):
    if not len(e):
        return np.zeros(0)
    d = v.shape[1]
    vol, L, _ = _scaled(v, e)
    regular = L**3 / (6 * sqrt(2)) if d == 3 else sqrt(3) / 4 * L**2
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.abs(vol) / regular
    return np.where(regular > 0, q, 0.0)


def orient(vertices, elements):
    """Re-orients negatively oriented elements by swapping their last two vertices.

    Returns ``(elements, flipped)``: a new (m, d + 1) int64 array and the (k,) indices of the
    elements swapped. Flat elements (signed volume exactly 0) are left as they are; see
    :func:`remove_slivers`."""
    v, e = _mesh(vertices, elements)
    e = e.copy()
    flipped = np.flatnonzero(_signed(v, e) < 0)
    e[flipped, -2], e[flipped, -1] = e[flipped, -1].copy(), e[flipped, -2].copy()
    return e, flipped


_orient = orient  # the functions below take a keyword of the same name


def _face_keys(e):
    """Sorted vertex tuples of every facet of every element, and the element of each, as a
    contiguous (m * (d + 1), d) array."""
    local = _TET_FACES if e.shape[1] == 4 else _TRI_EDGES
    faces = e[:, local].reshape(-1, local.shape[1])
    owner = np.repeat(np.arange(len(e)), len(local))
    return faces, owner


def _facet_counts(e):
    faces, owner = _face_keys(e)
    keys = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return faces, owner, counts[inverse.ravel()]


def remove_slivers(vertices, elements, *, min_quality=SLIVER_QUALITY):
    """Removes the elements of quality below ``min_quality`` (flat and near-flat elements).

    Returns ``(elements, removed, interior)``: the kept elements (input order), the (k,) indices of
    the removed ones and how many of those were interior (every facet shared with another
    element; see :class:`MeshReport`)."""
    v, e = _mesh(vertices, elements)
    q = real(min_quality, "min_quality")
    if not 0 <= q < 1:
        raise ValueError(f"min_quality: expected a value in [0, 1), got {min_quality!r}")
    bad = _quality(v, e) < q if q > 0 else np.zeros(len(e), bool)
    removed = np.flatnonzero(bad)
    interior = 0
    if removed.size:
        _, owner, shared = _facet_counts(e)
        all_shared = np.ones(len(e), bool)
        np.logical_and.at(all_shared, owner, shared > 1)
        interior = int(all_shared[removed].sum())
    return np.ascontiguousarray(e[~bad]), removed, interior


def clean(vertices, elements, *, orient=True, min_quality=SLIVER_QUALITY, drop_unused=False):
    """Makes a mesh acceptable to :class:`kinema.fem.Body`: removes slivers (quality below
    ``min_quality``; 0 keeps all), re-orients negatively oriented elements (``orient``)
    and, with ``drop_unused``, removes the vertices no element uses any more and renumbers.

    Returns ``(vertices, elements, report)``; ``report`` (:class:`MeshReport`) lists every change
    by the input's indices, and ``str(report)`` says it in one line."""
    v, e = _mesh(vertices, elements)
    report = MeshReport()
    keep = np.arange(len(e))
    if min_quality:
        e, report.slivers, report.interior_slivers = remove_slivers(v, e, min_quality=min_quality)
        keep = np.delete(keep, report.slivers)
    if orient:
        e, flipped = _orient(v, e)
        report.flipped = keep[flipped]
    if drop_unused:
        used = np.zeros(len(v), bool)
        used[e.ravel()] = True
        report.unused_vertices = np.flatnonzero(~used)
        vertex_map = np.full(len(v), -1, np.int64)
        vertex_map[used] = np.arange(int(used.sum()))
        report.vertex_map = vertex_map
        v, e = v[used], vertex_map[e]
    return np.ascontiguousarray(v), np.ascontiguousarray(e, dtype=np.int64), report


def surface(vertices, elements, *, orient=True) -> np.ndarray:
    """The boundary of a tetrahedral mesh as (F, 3) triangles with outward normals (right-hand
    rule), or of a triangle mesh as (F, 2) edges with the interior on their left (outer boundary
    counter-clockwise, holes clockwise).

    A boundary facet is one that belongs to exactly one element. With ``orient`` (the
    default) the facets take the orientation of the element after :func:`orient`, so a mesh with
    mis-oriented elements still gives an outward surface."""
    v, e = _mesh(vertices, elements)
    if orient:
        e, _ = _orient(v, e)
    faces, _, counts = _facet_counts(e)
    return np.ascontiguousarray(faces[counts == 1])


def boundary_edges(faces) -> np.ndarray:
    """(B, 2) edges of a triangle surface that belong to only one triangle (empty for a closed
    surface), as sorted vertex pairs."""
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {f.shape}")
    edges = np.sort(f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    return uniq[counts == 1]


def euler_characteristic(faces) -> int:
    """V - E + F of a triangle surface (V counts the vertices the faces use): 2 for a closed
    surface of genus 0, such as the surface of a box."""
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {f.shape}")
    edges = np.unique(np.sort(f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1), axis=0)
    return int(len(np.unique(f)) - len(edges) + len(f))


def surface_area(vertices, faces) -> float:
    """Total area of (F, 3) triangles (3D vertices) [m^2], or length of (F, 2) edges [m]."""
    v = as_float_array(vertices, "vertices", ndim=2)
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] not in (2, 3):
        raise ValueError(f"faces: expected shape (F, 3) or (F, 2), got {f.shape}")
    if f.shape[1] == 2:
        return float(np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1).sum())
    if v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (n, 3) for triangles, got {v.shape}")
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return float(0.5 * np.linalg.norm(n, axis=1).sum())
