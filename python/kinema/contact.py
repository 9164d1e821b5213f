"""Contact for soft bodies and cloth: Incremental Potential Contact (Li et al., ACM TOG 39(4),
2020), intersection-free by construction.

    scene = km.contact.Scene(gravity=(0, -9.81, 0), dhat=1e-3, friction=0.3)
    v, t = km.fem.box_mesh((0, 0.05, 0), (0.1, 0.15, 0.1), 3)
    cube = scene.add_solid(v, t, youngs_modulus=1e5, poisson_ratio=0.4, density=1000)
    scene.add_collider("plane", point=(0, 0, 0), normal=(0, 1, 0))
    for _ in range(100):
        stats = scene.step(1e-2)
    scene.x[cube]          # the cube's vertices, (n, 3) [m]

Each step is one implicit Euler step written as a minimisation (the course's ninth lecture,
Li et al. 2020 eq. 3)::

    x_{n+1} = argmin 1/2 |x - (x_n + h v_n + h^2 g)|_M^2 + h^2 (Psi(x) + D(x)) + kappa B(x)

with Psi the elastic energy of every body (stable neo-Hookean or another fem model on
tetrahedra, springs on cloth), B the log barrier summed over every pair of surface primitives
(vertex-triangle, edge-edge, reduced to vertex-edge and vertex-vertex by their closest points)
closer than ``dhat``, and D the Coulomb friction potential lagged at x_n (smoothed below the
slip speed ``friction_velocity``). Projected Newton solves it; every Newton step is clamped by
continuous collision detection (additive CCD, Li et al. 2021) before the backtracking line
search, so no step ever passes through anything: bodies never interpenetrate and never touch
(the gap stays positive; it is below dhat while in contact). A start that intersects is refused
with a ValueError naming the elements.

Colliders: infinite planes (exact half-spaces), and static triangle meshes: boxes, spheres
(icospheres whose vertices lie on the sphere), any mesh given as arrays or read by meshio.
Contact between bodies and self-contact use the same collision mesh: the boundary triangles of
each solid, every cloth triangle, every collider triangle.

Only 3D. The scene's state arrays are writable views; adding a body reallocates them (take
views again after an ``add_*``).
"""

from __future__ import annotations

import numpy as np

from kinema import _core
from kinema._checks import as_float_array, choice, finite, non_negative, positive

__all__ = ["Scene", "StepStats", "icosphere", "box_surface", "cloth_mesh", "MODELS"]

MODELS = ("linear", "stvk", "corotated", "neohookean")
StepStats = _core.contact.StepStats


def _indices(a, name, cols):
    arr = np.asarray(a)
    if arr.size == 0 and cols is None:
        return np.zeros(0, dtype=np.int64)
    if arr.dtype.kind not in "iu" and not (arr.dtype.kind == "f" and np.all(arr == np.round(arr))):
        raise ValueError(f"{name}: expected integer indices, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.int64)
    if cols is not None and (arr.ndim != 2 or arr.shape[1] != cols):
        raise ValueError(f"{name}: expected shape (m, {cols}), got {arr.shape}")
    if cols is None:
        arr = arr.reshape(-1)
    return arr


def _points(a, name):
    arr = as_float_array(a, name)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values")
    return np.ascontiguousarray(arr)


def _vec3(a, name):
    arr = as_float_array(a, name).reshape(-1)
    if arr.size != 3 or not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected 3 finite coordinates, got {np.asarray(a).tolist()!r}")
    return arr


def icosphere(center=(0.0, 0.0, 0.0), radius=1.0, subdivisions=3):
    """A triangulated sphere: the icosahedron subdivided ``subdivisions`` times with its
    vertices pushed onto the sphere. Returns (vertices (n, 3), triangles (m, 3)), outward
    oriented; faces lie inside the sphere by at most radius (1 - cos(edge angle / 2))."""
    c = _vec3(center, "center")
    r = positive(radius, "radius")
    if int(subdivisions) != subdivisions or not 0 <= subdivisions <= 7:
        raise ValueError(f"subdivisions: expected an integer in [0, 7], got {subdivisions!r}")
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(int(subdivisions)):
        cache = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        f = [tri for a, b, cc in f for tri in
             ((a, mid(a, b), mid(cc, a)), (b, mid(b, cc), mid(a, b)), (cc, mid(cc, a), mid(b, cc)),
              (mid(a, b), mid(b, cc), mid(cc, a)))]
    return c + r * np.array(verts), np.array(f, dtype=np.int64)


def box_surface(lower, upper):
    """The 12 outward-oriented triangles of the box [lower, upper]: (vertices (8, 3),
    triangles (12, 3))."""
    lo, hi = _vec3(lower, "lower"), _vec3(upper, "upper")
    if not (hi > lo).all():
        raise ValueError(f"lower, upper: expected lower < upper on every axis, got {lo.tolist()}, {hi.tolist()}")
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return corners, np.array(tris, dtype=np.int64)


def cloth_mesh(nx, ny, size, *, origin=(0.0, 0.0, 0.0), bending=True):
    """A square cloth in the plane y = origin[1]: (nx + 1) x (ny + 1) vertices spanning
    ``size`` (a number or (sx, sz)) from ``origin`` along x and z, two triangles per cell.
    Returns (vertices, triangles, springs): springs along every triangle edge, plus bending
    springs joining every second vertex along both grid axes when ``bending``."""
    if int(nx) != nx or int(ny) != ny or nx < 1 or ny < 1:
        raise ValueError(f"nx, ny: expected integers >= 1, got {nx!r}, {ny!r}")
    nx, ny = int(nx), int(ny)
    sx, sz = (size, size) if np.ndim(size) == 0 else tuple(size)
    positive(sx, "size")
    positive(sz, "size")
    o = _vec3(origin, "origin")
    I, J = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij")
    verts = np.stack([o[0] + sx * I.ravel() / nx, np.full(I.size, o[1]), o[2] + sz * J.ravel() / ny], 1)
    vid = lambda i, j: i * (ny + 1) + j  # noqa: E731
    ci, cj = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"))
    a, b, c, d = vid(ci, cj), vid(ci + 1, cj), vid(ci + 1, cj + 1), vid(ci, cj + 1)
    tris = np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, c], 1)])
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    springs = [np.unique(edges, axis=0)]
    if bending:
        if nx >= 2:
            i2, j2 = (q.ravel() for q in np.meshgrid(np.arange(nx - 1), np.arange(ny + 1), indexing="ij"))
            springs.append(np.stack([vid(i2, j2), vid(i2 + 2, j2)], 1))
        if ny >= 2:
            i2, j2 = (q.ravel() for q in np.meshgrid(np.arange(nx + 1), np.arange(ny - 1), indexing="ij"))
            springs.append(np.stack([vid(i2, j2), vid(i2, j2 + 2)], 1))
    return verts, tris.astype(np.int64), np.concatenate(springs).astype(np.int64)


class Scene:
    """Several deformable bodies (tetrahedral solids, cloths) and colliders in contact.

    Keyword options (fixed once the scene is built):

    * ``gravity``: (3,) [m/s^2], or None for no gravity.
    * ``dhat``: barrier activation distance [m]; pairs closer than this repel. Keep it well
      below the smallest feature (edge length, gap between bodies) of the meshes.
    * ``friction``: Coulomb coefficient mu (0: frictionless); ``friction_velocity``: slip speed
      eps_v [m/s] below which friction is smoothed (static friction is resolved to creep slower
      than eps_v).
    * ``barrier_stiffness``: kappa [J/m^4]; None picks IPC's mass-based value and raises it
      when contacts get closer than 1e-9 of the scene size.
    * ``tol``: Newton stops when ``max |dx| / dt < tol * (bounding-box diagonal)`` [1/s];
      ``max_newton``: its iteration cap (``km.ConvergenceError`` beyond it).
    * ``linear_solver``: "cholmod" (direct) or "cg".

    Attributes: ``x`` (n, 3) positions [m] and ``v`` (n, 3) velocities [m/s] of every vertex of
    every body and collider, in the order added (writable views; ``add_*`` returns each
    body's slice), ``time`` [s], ``mass`` (n,) [kg] (0 for collider vertices), ``faces``,
    ``edges`` of the collision mesh.
    """

    def __init__(self, *, gravity=None, dhat=1e-3, friction=0.0, friction_velocity=1e-3,
                 barrier_stiffness=None, tol=1e-2, max_newton=500, linear_solver="cholmod"):
        cfg = _core.contact.Config()
        cfg.gravity = (0.0, 0.0, 0.0) if gravity is None else tuple(_vec3(gravity, "gravity"))
        cfg.dhat = positive(dhat, "dhat")
        cfg.friction = non_negative(friction, "friction")
        cfg.friction_velocity = positive(friction_velocity, "friction_velocity")
        cfg.barrier_stiffness = 0.0 if barrier_stiffness is None else positive(barrier_stiffness, "barrier_stiffness")
        cfg.tol = positive(tol, "tol")
        if int(max_newton) != max_newton or max_newton < 1:
            raise ValueError(f"max_newton: expected an integer >= 1, got {max_newton!r}")
        cfg.max_newton = int(max_newton)
        cfg.linear_solver = choice(linear_solver, "linear_solver", ("cholmod", "cg"))
        self._core = _core.contact.Scene(cfg)
        self.config = cfg
        self.planes = []

    # ------------------------------------------------------------------ building

    def _slice(self, start, count):
        return slice(int(start), int(start) + int(count))

    def add_solid(self, vertices, tets, *, youngs_modulus, poisson_ratio, density, model="neohookean",
                  fixed=()) -> slice:
        """A tetrahedral solid (positively oriented tets, e.g. from ``km.fem.box_mesh``) with
        the given fem ``model``, Young's modulus [Pa], Poisson ratio and density [kg/m^3];
        ``fixed``: indices (into ``vertices``) held in place. Returns its rows of ``x``."""
        v = _points(vertices, "vertices")
        t = _indices(tets, "tets", 4)
        start = self._core.add_solid(v, t, choice(model, "model", MODELS), finite(youngs_modulus, "youngs_modulus"),
                                     finite(poisson_ratio, "poisson_ratio"), finite(density, "density"),
                                     _indices(fixed, "fixed", None))
        return self._slice(start, len(v))

    def add_cloth(self, vertices, triangles, *, stiffness, density, springs=None, fixed=()) -> slice:
        """A cloth: triangles (collision surface and mass, ``density`` in kg/m^2) and springs of
        ``stiffness`` [N/m] (default: the triangle edges; ``cloth_mesh`` adds bending springs).
        ``fixed``: pinned vertex indices. Returns its rows of ``x``."""
        v = _points(vertices, "vertices")
        tri = _indices(triangles, "triangles", 3)
        if springs is None:
            e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
            springs = np.unique(e, axis=0)
        start = self._core.add_cloth(v, tri, _indices(springs, "springs", 2), finite(stiffness, "stiffness"),
                                     finite(density, "density"), _indices(fixed, "fixed", None))
        return self._slice(start, len(v))

    def add_collider(self, shape, **kw):
        """A static collider. ``shape``:

        * "plane": ``point``, ``normal`` (pointing to the free side): an exact half-space;
        * "box": ``lower``, ``upper``: a solid box (12 triangles);
        * "sphere": ``center``, ``radius``, ``subdivisions`` (default 3): an icosphere;
        * "mesh": ``vertices`` and ``triangles``, or ``path`` to a file meshio reads
          (triangle cells).

        Returns the collider's rows of ``x`` (None for a plane)."""
        shape = choice(shape, "shape", ("plane", "box", "sphere", "mesh"))
        allowed = {"plane": {"point", "normal"}, "box": {"lower", "upper"},
                   "sphere": {"center", "radius", "subdivisions"}, "mesh": {"vertices", "triangles", "path"}}[shape]
        unknown = set(kw) - allowed
        if unknown:
            raise ValueError(f"{sorted(unknown)[0]}: not an option of a {shape} collider (expected {sorted(allowed)})")
        if shape == "plane":
            point, normal = _vec3(kw.get("point", (0, 0, 0)), "point"), _vec3(kw.get("normal", (0, 1, 0)), "normal")
            if np.linalg.norm(normal) == 0:
                raise ValueError("normal: expected a non-zero vector")
            self._core.add_plane(tuple(point), tuple(normal))
            self.planes.append((point, normal / np.linalg.norm(normal)))
            return None
        if shape == "box":
            v, t = box_surface(kw["lower"], kw["upper"])
        elif shape == "sphere":
            v, t = icosphere(kw.get("center", (0, 0, 0)), kw["radius"], kw.get("subdivisions", 3))
        elif "path" in kw:
            import meshio
            m = meshio.read(kw["path"])
            tris = [c.data for c in m.cells if c.type == "triangle"]
            if not tris:
                raise ValueError(f"path: {kw['path']!r} holds no triangle cells")
            v, t = m.points[:, :3], np.concatenate(tris)
        else:
            v, t = kw["vertices"], kw["triangles"]
        v = _points(v, "vertices")
        start = self._core.add_obstacle(v, _indices(t, "triangles", 3))
        return self._slice(start, len(v))

    # ------------------------------------------------------------------ stepping

    def step(self, dt) -> StepStats:
        """One implicit Euler step of ``dt`` [s]: returns the StepStats (Newton iterations,
        contact count, minimum distance [m], sticking and sliding friction contacts, CCD share
        of the wall time)."""
        return self._core.step(positive(dt, "dt"))

    def advance(self, duration, dt, *, on_step=None) -> int:
        """Steps of ``dt`` until ``duration`` has passed (the last one shortened to land on it);
        ``on_step(stats)`` is called after each. Returns the number of steps."""
        duration = non_negative(duration, "duration")
        dt = positive(dt, "dt")
        end = self.time + duration
        steps = 0
        while end - self.time > 1e-12 * max(1.0, abs(end)):
            h = min(dt, end - self.time)
            if end - self.time - h < 0.1 * dt:
                h = end - self.time
            stats = self.step(h)
            steps += 1
            if on_step is not None:
                on_step(stats)
        return steps

    # ------------------------------------------------------------------ state

    @property
    def x(self) -> np.ndarray:
        """(n, 3) vertex positions [m] (a writable view)."""
        return self._core.x

    @x.setter
    def x(self, value):
        self._core.x[...] = _points(value, "x").reshape(self._core.x.shape)
        self._core.kappa = 0.0  # re-check the new positions for intersections at the next step

    @property
    def v(self) -> np.ndarray:
        """(n, 3) vertex velocities [m/s] (a writable view)."""
        return self._core.v

    @v.setter
    def v(self, value):
        self._core.v[...] = _points(value, "v").reshape(self._core.v.shape)

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._core.time

    @property
    def mass(self) -> np.ndarray:
        """(n,) lumped vertex masses [kg]; 0 for collider vertices."""
        return np.asarray(self._core.mass)

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) triangles of the collision mesh (global vertex indices)."""
        return self._core.faces

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) edges of the collision mesh."""
        return self._core.edges

    parameters = ()

    def state(self) -> dict:
        """Copies of everything that evolves: x, v, time and the barrier stiffness in use."""
        return {"x": self.x.copy(), "v": self.v.copy(), "time": self.time, "kappa": self._core.kappa}

    def set_state(self, state: dict) -> None:
        """Restores a ``state()`` exactly (the run continues bitwise as the one not stopped)."""
        self._core.x[...] = _points(state["x"], "x")
        self._core.v[...] = _points(state["v"], "v")
        self._core.time = float(state["time"])
        self._core.kappa = float(state["kappa"])

    # ------------------------------------------------------------------ diagnostics

    def min_distance(self, radius=None, x=None) -> float:
        """Exact smallest distance [m] between non-adjacent primitives of the collision mesh
        (vertex-triangle, edge-edge) and from vertices to planes, over the pairs closer than
        ``radius`` (default 10 dhat); inf when none is that close."""
        r = 10 * self.config.dhat if radius is None else positive(radius, "radius")
        return self._core.min_distance(self.x if x is None else _points(x, "x"), r)

    def intersections(self, x=None, limit=10) -> list:
        """Descriptions of intersecting edge-triangle pairs and vertices behind planes (empty
        when the configuration is intersection-free)."""
        return self._core.intersections(self.x if x is None else _points(x, "x"), int(limit))

    def kinetic_energy(self) -> float:
        """``1/2 sum m |v|^2`` [J]."""
        return 0.5 * float(np.sum(self.mass * np.sum(self.v ** 2, axis=1)))

    def momentum(self) -> np.ndarray:
        """Linear momentum sum m v (3,) [kg m/s]."""
        return (self.mass[:, None] * self.v).sum(axis=0)

    def elastic_energy(self, x=None) -> float:
        """Elastic energy Psi [J] of every body at x (default: the current positions)."""
        return self._core.elastic_energy(self.x if x is None else _points(x, "x"))

    def potential_energy(self) -> float:
        """Elastic plus gravitational energy [J] (gravity's zero at the origin)."""
        g = np.asarray(self.config.gravity)
        return self.elastic_energy() - float(np.sum(self.mass * (self.x @ g)))

    def barrier_energy(self, x=None) -> float:
        """sum_k b(d_k) over the active pairs (squared distances, [m^4])."""
        return self._core.barrier_energy(self.x if x is None else _points(x, "x"))

    def barrier_gradient(self, x=None) -> np.ndarray:
        """Gradient (n, 3) of ``barrier_energy``."""
        return self._core.barrier_gradient(self.x if x is None else _points(x, "x"))

    def barrier_hessian(self, x=None, *, project=False):
        """Hessian (3n, 3n) scipy.sparse.csr_matrix of ``barrier_energy`` (per-contact PSD
        projection when ``project``)."""
        import scipy.sparse as sp
        val, col, ptr = self._core.barrier_hessian(self.x if x is None else _points(x, "x"), bool(project))
        n = 3 * self._core.vertex_count
        return sp.csr_matrix((val, col, ptr), shape=(n, n))

    def max_safe_step(self, dx, x=None) -> float:
        """Largest t in [0, 1] for which moving x -> x + t dx is intersection-free (additive
        CCD, conservative)."""
        return self._core.max_safe_step(self.x if x is None else _points(x, "x"), _points(dx, "dx"))
