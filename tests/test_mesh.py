"""km.mesh: orientation fixing, sliver removal and surface extraction, on meshes built so that the
right answer is known (flips and slivers put in by hand, a box whose surface is known)."""

import numpy as np
import pytest

import kinema as km


def box(n=(3, 2, 2), lower=(0.0, 0.0, 0.0), upper=(1.5, 1.0, 0.5), tets_per_cell=6):
    return km.fem.box_mesh(lower, upper, n, tets_per_cell=tets_per_cell)


def flip(elements, which):
    e = elements.copy()
    e[which, 0], e[which, 1] = elements[which, 1], elements[which, 0]
    return e


@pytest.mark.parametrize("d", [2, 3])
def test_orient_fixes_exactly_the_flipped_elements(d):
    v, e = km.fem.rectangle_mesh((0, 0), (2, 1), (4, 3)) if d == 2 else box()
    assert (km.mesh.signed_volumes(v, e) > 0).all()
    which = np.array([0, 5, len(e) - 1])
    bad = flip(e, which)
    vol = km.mesh.signed_volumes(v, bad)
    assert np.array_equal(np.flatnonzero(vol < 0), which)
    fixed, flipped = km.mesh.orient(v, bad)
    assert np.array_equal(flipped, which)
    assert np.allclose(km.mesh.signed_volumes(v, fixed), km.mesh.signed_volumes(v, e), rtol=1e-14)
    # same vertex sets: the fix re-orders, it does not re-mesh
    assert np.array_equal(np.sort(fixed, axis=1), np.sort(e, axis=1))
    again, none = km.mesh.orient(v, fixed)
    assert none.size == 0 and np.array_equal(again, fixed)


def test_fem_body_orient_option_and_hint():
    v, e = box()
    bad = flip(e, [2, 7])
    with pytest.raises(ValueError, match="inverted.*orient=True"):
        km.fem.Body(v, bad, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    body = km.fem.Body(v, bad, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0, orient=True)
    assert body.flipped.tolist() == [2, 7]
    ref = km.fem.Body(v, e, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    # re-oriented elements give the same body: same masses and forces at a deformed state
    assert np.allclose(body.mass, ref.mass, rtol=1e-14)
    rng = np.random.default_rng(0)
    dx = 0.01 * rng.standard_normal(v.shape)
    body.x[:] += dx
    ref.x[:] += dx
    assert np.allclose(body.forces(), ref.forces(), rtol=1e-10, atol=1e-12 * np.abs(ref.forces()).max())


def sliver_mesh():
    """A unit cube in 6 tets plus: a flat tet on the face z = 0 (its 4 corners, quality 0), a
    near-flat one on the face x = 1 with a vertex lifted by 1e-9 out of the plane, and a good
    tet standing on the face y = 1 (apex outside the cube)."""
    v, e = box(n=1, upper=(1.0, 1.0, 1.0))
    vid = {tuple(p): i for i, p in enumerate(np.round(v).astype(int))}
    extra_v = np.array([[1.0 + 1e-9, 0.5, 0.5], [0.5, 2.0, 0.5]])
    v = np.vstack([v, extra_v])
    a, b = len(v) - 2, len(v) - 1
    flat = [vid[0, 0, 0], vid[1, 0, 0], vid[1, 1, 0], vid[0, 1, 0]]
    near = [vid[1, 0, 0], vid[1, 1, 0], vid[1, 1, 1], a]
    good = [vid[0, 1, 0], vid[1, 1, 0], vid[0, 1, 1], b]
    e = np.vstack([e, [flat, near, good]])
    e, _ = km.mesh.orient(v, e)  # the flat one (volume exactly 0) stays as it is
    return v, e


def test_remove_slivers_reports_what_it_removed():
    v, e = sliver_mesh()
    q = km.mesh.quality(v, e)
    assert q[6] == 0 and 0 < q[7] < 1e-6 and q[8] > 0.1 and (q[:6] > 0.1).all()
    kept, removed, interior = km.mesh.remove_slivers(v, e)
    assert removed.tolist() == [6, 7] and interior == 0
    assert np.array_equal(kept, e[[0, 1, 2, 3, 4, 5, 8]])
    # a stricter threshold removes only what it must
    _, removed, _ = km.mesh.remove_slivers(v, e, min_quality=1e-12)
    assert removed.tolist() == [6]
    with pytest.raises(ValueError, match="min_quality"):
        km.mesh.remove_slivers(v, e, min_quality=2.0)


def test_clean_slivers_flips_and_unused_vertices_then_body_accepts():
    v, e = sliver_mesh()
    e = flip(e, [1, 8])
    with pytest.raises(ValueError, match="degenerate.*km.mesh.clean"):
        km.fem.Body(v, e, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0, orient=True)
    v2, e2, report = km.mesh.clean(v, e, drop_unused=True)
    assert report.slivers.tolist() == [6, 7]
    assert report.flipped.tolist() == [1, 8]  # indices into the input, not the kept elements
    assert report.unused_vertices.tolist() == [8]  # the lifted vertex only served the sliver
    assert len(v2) == len(v) - 1 and report.vertex_map[8] == -1
    assert "2 sliver(s) removed [6, 7]" in str(report) and "re-oriented [1, 8]" in str(report)
    assert (km.mesh.signed_volumes(v2, e2) > 0).all()
    total = km.mesh.signed_volumes(v2, e2).sum()
    assert total == pytest.approx(1.0 + 0.5 * 1.0 / 3.0, rel=1e-14)  # cube + pyramid-half tet
    km.fem.Body(v2, e2, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    assert str(km.mesh.clean(v2, e2)[2]) == "mesh unchanged"


def outward_volume(v, faces):
    """Divergence theorem: the volume enclosed by outward triangles, sum (x_c . n_f) A_f / 3."""
    p0, p1, p2 = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->", p0, np.cross(p1 - p0, p2 - p0)) / 6.0)


@pytest.mark.parametrize("tets_per_cell", [5, 6])
def test_box_surface_closed_genus_zero_area_and_outward(tets_per_cell):
    lo, hi = np.array([0.0, -1.0, 0.5]), np.array([2.0, 0.5, 1.25])
    v, e = km.fem.box_mesh(lo, hi, (4, 3, 2), tets_per_cell=tets_per_cell)
    e = flip(e, np.arange(0, len(e), 3))  # mis-oriented input: the surface must not care
    f = km.mesh.surface(v, e)
    a, b, c = hi - lo
    nx, ny, nz = 4, 3, 2
    assert len(f) == 4 * (nx * ny + ny * nz + nz * nx)  # 2 triangles per boundary square
    assert km.mesh.boundary_edges(f).shape == (0, 2)  # closed
    # consistently oriented: every directed edge once, its reverse once
    directed = f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    assert len(np.unique(directed, axis=0)) == len(directed)
    assert km.mesh.euler_characteristic(f) == 2
    assert km.mesh.surface_area(v, f) == pytest.approx(2 * (a * b + b * c + c * a), rel=1e-13)
    assert outward_volume(v, f) == pytest.approx(a * b * c, rel=1e-13)  # > 0: outward
    # every surface vertex lies on the box's boundary
    on = np.isclose(v[np.unique(f)], lo).any(1) | np.isclose(v[np.unique(f)], hi).any(1)
    assert on.all()


def test_surface_of_a_triangle_mesh_is_its_counter_clockwise_boundary():
    v, e = km.fem.rectangle_mesh((0, 0), (3, 2), (3, 2))
    edges = km.mesh.surface(v, flip(e, [0, 3]))
    assert edges.shape == (2 * (3 + 2), 2)
    assert km.mesh.surface_area(v, edges) == pytest.approx(10.0, rel=1e-14)
    # counter-clockwise: the shoelace sum over the boundary edges is the enclosed area
    p, q = v[edges[:, 0]], v[edges[:, 1]]
    assert 0.5 * np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]) == pytest.approx(6.0, rel=1e-14)


def test_surface_of_two_disjoint_boxes_and_a_hole():
    v1, e1 = box(n=2)
    v2, e2 = box(n=2, lower=(3.0, 0.0, 0.0), upper=(4.0, 1.0, 1.0))
    v = np.vstack([v1, v2])
    e = np.vstack([e1, e2 + len(v1)])
    f = km.mesh.surface(v, e)
    assert km.mesh.euler_characteristic(f) == 4  # two spheres
    # a 3x3x3 block of cells without its centre cell: outer box plus an inward-facing cavity
    v, e = box(n=3, upper=(3.0, 3.0, 3.0))
    centroid = v[e].mean(axis=1)
    keep = ~((centroid > 1).all(1) & (centroid < 2).all(1))
    f = km.mesh.surface(v, e[keep])
    assert km.mesh.euler_characteristic(f) == 4
    assert km.mesh.surface_area(v, f) == pytest.approx(54.0 + 6.0, rel=1e-13)
    assert outward_volume(v, f) == pytest.approx(27.0 - 1.0, rel=1e-13)


def test_bad_input_is_a_clear_value_error():
    v, e = box(n=1)
    with pytest.raises(ValueError, match="elements: expected shape"):
        km.mesh.orient(v, e[:, :3])
    with pytest.raises(ValueError, match="vertex indices"):
        km.mesh.surface(v, e + 100)
    with pytest.raises(ValueError, match="repeats a vertex"):
        km.mesh.clean(v, np.array([[0, 0, 1, 2]]))
    with pytest.raises(ValueError, match="vertices"):
        km.mesh.orient(np.zeros((4, 4)), e[:1])
    with pytest.raises(ValueError, match="non-finite"):
        km.mesh.quality(np.full_like(v, np.nan), e)
