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

Colliders, static or scripted (``velocity``, ``angular_velocity`` or a ``motion`` function of
the time): infinite planes (exact half-spaces; a moving plane translates, its normal fixed) and
triangle meshes: boxes, spheres (icospheres whose vertices lie on the sphere), any mesh given as
arrays or read by meshio.
Contact between bodies and self-contact use the same collision mesh: the boundary triangles of
each solid, every cloth triangle, every collider triangle.

Only 3D. The scene's state arrays are writable views; adding a body reallocates them (take
views again after an ``add_*``).
"""

from __future__ import annotations

import numpy as np

from kinema import _core
from kinema._checks import INT_MAX, as_float_array, choice, finite, integer, non_negative, positive, time_step
from kinema.errors import DivergenceError

__all__ = ["Scene", "BodyContact", "attach", "StepStats", "icosphere", "box_surface", "cloth_mesh", "MODELS"]

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
    subdivisions = integer(subdivisions, "subdivisions", low=0, high=7)
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


def _required(shape, kw):
    """Refuses a collider missing an option its shape needs (ValueError naming it)."""
    need = {"box": ("lower", "upper"), "sphere": ("radius",), "plane": ()}.get(shape)
    if shape == "mesh":
        if "path" in kw and ("vertices" in kw or "triangles" in kw):
            raise ValueError("path: a mesh collider takes either path or vertices and triangles, not both")
        need = ("path",) if "path" in kw else ("vertices", "triangles")
    for key in need:
        if key not in kw:
            raise ValueError(f"{key}: a {shape} collider needs {' and '.join(need)}")


def _surface(shape, kw):
    """(vertices (n, 3), triangles (m, 3)) of a box, sphere or mesh collider, checked."""
    _required(shape, kw)
    if shape == "box":
        v, t = box_surface(kw["lower"], kw["upper"])
    elif shape == "sphere":
        v, t = icosphere(kw.get("center", (0, 0, 0)), kw["radius"], kw.get("subdivisions", 3))
    elif "path" in kw:
        import meshio
        path = kw["path"]
        if not isinstance(path, (str, bytes)) and not hasattr(path, "__fspath__"):
            raise ValueError(f"path: expected a file name, got {path!r}")
        try:
            m = meshio.read(path)
        except Exception as exc:  # noqa: BLE001 - meshio raises many types for unreadable files
            raise ValueError(f"path: cannot read {str(path)!r} as a mesh ({type(exc).__name__}: {exc})") from None
        tris = [c.data for c in m.cells if c.type == "triangle"]
        if not tris:
            raise ValueError(f"path: {path!r} holds no triangle cells")
        v, t = m.points[:, :3], np.concatenate(tris)
    else:
        v, t = kw["vertices"], kw["triangles"]
    return _points(v, "vertices"), _indices(t, "triangles", 3)  # index ranges are checked in C++


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
    * ``linear_solver``: "simplicial" (default: a direct solve per Newton iteration by a
      simplicial Cholesky on 3x3 blocks, fastest on contact scenes of up to a few thousand
      vertices), "cholmod" (the same by CHOLMOD's supernodal factorisation), "cholmod-pcg" (PCG
      preconditioned by the last factor, refactorised when PCG stalls) or "cg" (Jacobi).
    * ``reuse_pattern``: keep the Newton matrix's sparsity pattern (elastic blocks plus the
      contact blocks seen so far) and its symbolic analysis between Newton iterations and
      steps (default); False re-analyses whenever the contact pattern changes (for
      comparisons: the results agree to rounding).
    * ``barrier_projection``: how each contact's barrier Hessian is made positive
      semidefinite in the Newton matrix: "rank-one" (default: max(b'' + b' / (2 d), 0)
      grad d grad d^T, the clamped distance-normal term, no eigenproblem; exact for
      vertex-vertex and vertex-plane pairs, within ``|2 s b'| |Hess s|`` of the clamp
      otherwise, relatively about gap / edge length) or "clamp" (each contact's negative
      eigenvalues clamped to zero, Li et al. 2020). The gradient is exact either way, so
      Newton stops at the same minimiser to ``tol``.

    Attributes: ``x`` (n, 3) positions [m] and ``v`` (n, 3) velocities [m/s] of every vertex of
    every body and collider, in the order added (writable views; ``add_*`` returns each
    body's slice), ``time`` [s], ``mass`` (n,) [kg] (0 for collider vertices), ``faces``,
    ``edges`` of the collision mesh.
    """

    def __init__(self, *, gravity=None, dhat=1e-3, friction=0.0, friction_velocity=1e-3,
                 barrier_stiffness=None, tol=1e-2, max_newton=500, linear_solver="simplicial",
                 reuse_pattern=True, barrier_projection="rank-one"):
        cfg = _core.contact.Config()
        cfg.gravity = (0.0, 0.0, 0.0) if gravity is None else tuple(_vec3(gravity, "gravity"))
        cfg.dhat = positive(dhat, "dhat")
        cfg.friction = non_negative(friction, "friction")
        cfg.friction_velocity = positive(friction_velocity, "friction_velocity")
        cfg.barrier_stiffness = 0.0 if barrier_stiffness is None else positive(barrier_stiffness, "barrier_stiffness")
        cfg.tol = positive(tol, "tol")
        cfg.max_newton = integer(max_newton, "max_newton", low=1, high=INT_MAX)
        cfg.linear_solver = choice(linear_solver, "linear_solver", ("simplicial", "cholmod", "cholmod-pcg", "cg"))
        if not isinstance(reuse_pattern, (bool, np.bool_)):
            raise ValueError(f"reuse_pattern: expected True or False, got {reuse_pattern!r}")
        cfg.reuse_pattern = bool(reuse_pattern)
        cfg.barrier_projection = choice(barrier_projection, "barrier_projection", ("rank-one", "clamp"))
        self._core = _core.contact.Scene(cfg)
        self.config = cfg
        self.planes = []
        self.colliders = []  # dicts: shape, options, rows, rest, pivot, motion, script (the argument naming it)
        self._bodies = []

    # ------------------------------------------------------------------ building

    def _slice(self, start, count):
        return slice(int(start), int(start) + int(count))

    def add_solid(self, vertices, tets, *, youngs_modulus, poisson_ratio, density, model="neohookean",
                  fixed=(), damping=0.0) -> slice:
        """A tetrahedral solid (positively oriented tets, e.g. from ``km.fem.box_mesh``) with
        the given fem ``model``, Young's modulus [Pa] and Poisson ratio (scalars or one per
        tet), density [kg/m^3] and mass-proportional ``damping`` c [1/s] (as km.fem.Body);
        ``fixed``: indices (into ``vertices``) held in place. Returns its rows of ``x``."""
        v = _points(vertices, "vertices")
        t = _indices(tets, "tets", 4)
        E = np.ascontiguousarray(np.atleast_1d(as_float_array(youngs_modulus, "youngs_modulus")).ravel())
        nu = np.ascontiguousarray(np.atleast_1d(as_float_array(poisson_ratio, "poisson_ratio")).ravel())
        if nu.size == 1 and E.size > 1:
            nu = np.full(E.size, nu[0])
        if E.size == 1 and nu.size > 1:
            E = np.full(nu.size, E[0])
        start = self._core.add_solid(v, t, choice(model, "model", MODELS), E, nu, finite(density, "density"),
                                     finite(damping, "damping"), _indices(fixed, "fixed", None))
        return self._slice(start, len(v))

    def add_body(self, body, *, triangles=None) -> slice:
        """A ``km.fem.Body`` (3D tetrahedra) or ``km.massspring.System`` (3D) with its own
        material, masses, fixed vertices and damping; after every step of the scene its ``x``
        and ``v`` (and time) hold the body's part of the result, and values written into them
        before a step are what the step starts from. ``triangles`` (mass-spring only): the
        collision surface (e.g. ``km.massspring.cloth(...).triangles``); without it the
        vertices collide as points. The body's gravity must be the scene's. Returns its rows."""
        from kinema import fem, massspring

        if any(b is body for b, _ in self._bodies):
            raise ValueError("body: this body is already in the scene (a body is added once)")
        if isinstance(body, (fem.Body, massspring.System)):
            _points(body.x, "body.x"), as_float_array(body.v, "body.v")
        if isinstance(body, fem.Body):
            if body.x.shape[1] != 3:
                raise ValueError("body: contact is 3D only; got a 2D km.fem.Body")
            if triangles is not None:
                raise ValueError("triangles: a km.fem.Body collides with its boundary surface; do not pass triangles")
            self._check_gravity(body._gravity, "body")
            vals = body._values
            rows = self.add_solid(body.rest, body.elements, youngs_modulus=vals["youngs_modulus"],
                                  poisson_ratio=vals["poisson_ratio"], density=vals["density"], model=body.model,
                                  fixed=body.fixed, damping=vals["damping"])
        elif isinstance(body, massspring.System):
            if body.x.shape[1] != 3:
                raise ValueError("body: contact is 3D only; got a 2D km.massspring.System")
            self._check_gravity(body.gravity, "body")
            p = {k: np.ascontiguousarray(body._core.parameter(k), dtype=float)
                 for k in ("stiffness", "rest_length", "damping", "mass")}
            tri = np.zeros((0, 3), np.int64) if triangles is None else _indices(triangles, "triangles", 3)
            start = self._core.add_springs(_points(body.x, "body.x"), _indices(body.springs, "springs", 2),
                                           p["stiffness"], p["rest_length"], p["damping"], p["mass"], tri,
                                           _indices(body.fixed, "fixed", None))
            rows = self._slice(start, len(body.x))
        else:
            raise ValueError(f"body: expected a km.fem.Body or km.massspring.System, got {type(body).__name__}")
        self._core.x[rows] = body.x
        self._core.v[rows] = body.v
        self._bodies.append((body, rows))
        return rows

    def _check_gravity(self, g, name):
        g = np.zeros(3) if g is None or len(g) == 0 else np.asarray(g, float)
        if not np.allclose(g, self.config.gravity, rtol=0, atol=0):
            raise ValueError(f"{name}: its gravity {g.tolist()} differs from the scene's "
                             f"{list(self.config.gravity)}; a scene has one gravity")

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

    def add_collider(self, shape, *, motion=None, velocity=None, angular_velocity=None, friction=None, **kw):
        """A collider, static or moving, with its own Coulomb coefficient ``friction`` for every
        contact with it (default None: the scene's ``friction``). ``shape``:

        * "plane": ``point``, ``normal`` (pointing to the free side): an exact half-space;
          a moving plane translates (its normal is fixed: ``velocity``, or a ``motion``
          whose rotations, if any, turn about the normal), its point being one driven row of
          ``x``;
        * "box": ``lower``, ``upper``: a solid box (12 triangles);
        * "sphere": ``center``, ``radius``, ``subdivisions`` (default 3): an icosphere;
        * "mesh": ``vertices`` and ``triangles``, or ``path`` to a file meshio reads
          (triangle cells).

        Moving (scripted) colliders: ``velocity`` (3,) [m/s] and/or ``angular_velocity``
        (3,) [rad/s] about the collider's centre, or ``motion``: a function of the time t [s]
        returning a translation (3,) or a pair (R (3, 3), translation): the collider's vertices
        at t are ``R (x0 - c) + c + translation`` with x0 the given vertices and c their
        centre. Each step moves the collider's vertices from where they are to their place at
        the step's end inside the CCD-clamped solve (a stiff augmented-Lagrangian hold), so
        nothing passes through a moving collider either; what it pushes is pushed.

        Returns the collider's rows of ``x`` (None for a static plane; a moving plane's one
        row is its point)."""
        shape = choice(shape, "shape", ("plane", "box", "sphere", "mesh"))
        mu = -1.0 if friction is None else non_negative(friction, "friction")
        if angular_velocity is not None and shape == "plane":
            raise ValueError("angular_velocity: a plane collider moves by translation only (its normal is fixed)")
        script = "motion" if motion is not None else "velocity" if velocity is not None else "angular_velocity"
        motion = _motion(motion, velocity, angular_velocity)
        allowed = {"plane": {"point", "normal"}, "box": {"lower", "upper"},
                   "sphere": {"center", "radius", "subdivisions"}, "mesh": {"vertices", "triangles", "path"}}[shape]
        unknown = set(kw) - allowed
        if unknown:
            raise ValueError(f"{sorted(unknown)[0]}: not an option of a {shape} collider (expected {sorted(allowed)})")
        if shape == "plane":
            point, normal = _vec3(kw.get("point", (0, 0, 0)), "point"), _vec3(kw.get("normal", (0, 1, 0)), "normal")
            if not normal.any():
                raise ValueError("normal: expected a non-zero vector")
            normal = normal / np.abs(normal).max()  # its norm is then representable
            start = self._core.add_plane(tuple(point), tuple(normal), mu, motion is not None)
            unit = normal / np.linalg.norm(normal)
            self.planes.append((point, unit))
            rows = None if motion is None else self._slice(start, 1)
            spec = {"shape": "plane", "point": point, "normal": unit, "rows": rows, "motion": motion,
                    "rest": point[None, :].copy(), "pivot": point.copy(), "script": script}
            self.colliders.append(spec)
            if motion is not None:
                self._core.x[rows] = _place(spec, self.time)
            return rows
        v, t = _surface(shape, kw)
        start = self._core.add_obstacle(v, t, motion is not None, mu)
        rows = self._slice(start, len(v))
        spec = {"shape": shape, "rows": rows, "rest": v.copy(), "motion": motion,
                "pivot": 0.5 * (v.min(axis=0) + v.max(axis=0)), "script": script}
        if shape == "box":
            spec.update(lower=_vec3(kw["lower"], "lower"), upper=_vec3(kw["upper"], "upper"))
        elif shape == "sphere":
            spec.update(center=_vec3(kw.get("center", (0, 0, 0)), "center"), radius=float(kw["radius"]))
        self.colliders.append(spec)
        if motion is not None:
            self._core.x[rows] = _place(spec, self.time)
        return rows

    def collider_positions(self, index, time=None):
        """(k, 3) vertices [m] of collider ``index`` (in the order added) at ``time`` (default:
        now) by its script."""
        n = len(self.colliders)
        if n == 0:
            raise ValueError("index: the scene has no colliders")
        index = integer(index, "index", low=-n, high=n - 1)
        spec = self.colliders[index]
        if spec["rows"] is None:
            raise ValueError(f"index: collider {index} is a static plane (no vertices)")
        return _place(spec, self.time if time is None else finite(time, "time"))

    # ------------------------------------------------------------------ stepping

    def step(self, dt) -> StepStats:
        """One implicit Euler step of ``dt`` [s]: returns the StepStats (Newton iterations,
        contact count, minimum distance [m], sticking and sliding friction contacts, CCD share
        of the wall time)."""
        dt = time_step(dt)
        for body, rows in self._bodies:  # what the user wrote into a body's arrays counts
            if not np.array_equal(self._core.x[rows], body.x):
                self._core.x[rows] = body.x
                self._core.kappa = 0.0  # re-check for intersections
            self._core.v[rows] = body.v
        for name in ("x", "v"):
            bad = np.count_nonzero(~np.isfinite(getattr(self._core, name)))
            if bad:
                raise DivergenceError(f"{name}: {bad} non-finite value(s) at the start of the step (written into "
                                      "a view, or left by a diverged run)")
        target = self._core.target
        scale = None
        for spec in self.colliders:
            if spec["motion"] is not None:
                placed = _place(spec, self.time + dt)
                if scale is None:
                    scale = self._motion_scale()
                _check_reach(spec, self._core.x[spec["rows"]], placed, dt, scale)
                target[spec["rows"]] = placed
        try:
            stats = self._core.step(dt)
        except ValueError as exc:
            if not str(exc).startswith("A:"):
                raise
            # the Newton matrix M / dt^2 + H(elastic) + kappa H(barrier) overflowed
            raise ValueError(f"dt, dhat: the Newton matrix of this step is not finite ({exc}): dt, dhat, "
                             "barrier_stiffness or a material value is out of range for this scene") from None
        for body, rows in self._bodies:
            body.x[...] = self._core.x[rows]
            body.v[...] = self._core.v[rows]
            _set_time(body, self.time)
        return stats

    def _motion_scale(self):
        """The scene size the solver measures a step's reach by: the bounding-box diagonal of
        every vertex but the moving planes' points, at least 1 m (as Solver::step)."""
        keep = np.ones(len(self._core.x), bool)
        for spec in self.colliders:
            if spec["shape"] == "plane" and spec["rows"] is not None:
                keep[spec["rows"]] = False
        x = self._core.x[keep]
        return max(float(np.linalg.norm(x.max(axis=0) - x.min(axis=0))) if len(x) else 0.0, 1.0)

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
        """Hessian (3n, 3n) scipy.sparse.csr_matrix of ``barrier_energy``, made positive
        semidefinite per contact when ``project``: True or "clamp" (negative eigenvalues of each
        contact's Hessian clamped to zero, the nearest PSD matrix), "rank-one" (the Gauss-Newton
        matrix max(b'' + b' / (2 d), 0) grad d grad d^T the solver assembles by default, within
        |2 s b'| |Hess s| of the clamp in Frobenius norm; see ``barrier_projection``)."""
        import scipy.sparse as sp
        how = {False: "none", True: "clamp"}.get(project, project) if isinstance(project, (bool, np.bool_)) else project
        how = choice(how, "project", ("none", "clamp", "rank-one"))
        val, col, ptr = self._core.barrier_hessian(self.x if x is None else _points(x, "x"), how)
        n = 3 * self._core.vertex_count
        return sp.csr_matrix((val, col, ptr), shape=(n, n))

    def max_safe_step(self, dx, x=None) -> float:
        """Largest t in [0, 1] for which moving x -> x + t dx is intersection-free (additive
        CCD, conservative)."""
        return self._core.max_safe_step(self.x if x is None else _points(x, "x"), _points(dx, "dx"))


# ---------------------------------------------------------------------- moving colliders

def _rotation(w, t):
    """exp(t [w]x) by Rodrigues' formula."""
    theta = np.linalg.norm(w) * t
    if theta == 0:
        return np.eye(3)
    k = w / np.linalg.norm(w)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _motion(motion, velocity, angular_velocity):
    """The script t -> (R, translation) of a moving collider, or None for a static one."""
    if motion is None and velocity is None and angular_velocity is None:
        return None
    if motion is not None:
        if velocity is not None or angular_velocity is not None:
            raise ValueError("motion: give either motion or velocity/angular_velocity, not both")
        if not callable(motion):
            raise ValueError(f"motion: expected a function of the time, got {type(motion).__name__}")

        def script(t):
            out = motion(t)
            if isinstance(out, tuple) and len(out) == 2:
                R = np.asarray(out[0], float)
                if R.shape != (3, 3) or not np.isfinite(R).all():
                    raise ValueError(f"motion: R at t = {t} is not a finite (3, 3) matrix")
                return R, _vec3(out[1], "motion")
            return np.eye(3), _vec3(out, "motion")
        return script
    v = np.zeros(3) if velocity is None else _vec3(velocity, "velocity")
    w = np.zeros(3) if angular_velocity is None else _vec3(angular_velocity, "angular_velocity")

    def script(t):
        with np.errstate(over="ignore"):  # an overflow is refused where the collider is placed
            return _rotation(w, t), v * t
    return script


def _check_reach(spec, now, placed, dt, scale):
    """Refuse a scripted collider motion that overflows or moves the collider by more than 1000
    scene diagonals in one step (the limit Solver::step puts on free vertices): its squared
    displacement would overflow the incremental potential (or CCD crawl along it for hours)."""
    with np.errstate(over="ignore", invalid="ignore"):
        reach = np.abs(placed - now).max() if placed.size else 0.0
    if not (np.isfinite(placed).all() and reach <= 1e3 * scale):
        raise ValueError(f"{spec['script']}: a step of dt = {dt:g} would move the {spec['shape']} collider by "
                         f"{reach:g} m, more than 1000 scene diagonals ({scale:g} m): its motion is out of range")


def _place(spec, t):
    """A collider's vertices at time t by its script."""
    if spec["motion"] is None:
        return spec["rest"]
    R, c = spec["motion"](t)
    p = spec["pivot"]
    if spec["shape"] == "plane" and not np.allclose(R @ spec["normal"], spec["normal"], rtol=0, atol=1e-12):
        raise ValueError(f"motion: at t = {t} it turns the plane's normal; a plane collider moves by translation "
                         "only (rotations about its normal are allowed)")
    with np.errstate(over="ignore", invalid="ignore"):  # refused just below
        placed = (spec["rest"] - p) @ R.T + p + c
    if not np.isfinite(placed).all():
        raise ValueError(f"{spec['script']}: at t = {t} it places the {spec['shape']} collider at non-finite "
                         "coordinates (the motion overflows)")
    return placed


def _set_time(body, t):
    if hasattr(body, "_state"):  # km.fem.Body
        body._state.time = t
    else:
        body._core.time = t


# ---------------------------------------------------------------------- colliders on one body

def attach(sim, *, dhat=None, friction=0.0, friction_velocity=1e-3, tol=1e-2, max_newton=500, triangles=None,
           barrier_stiffness=None):
    """The :class:`BodyContact` of a ``km.fem.Body`` or ``km.massspring.System`` (made on first
    use; its options are set when it is made and may be given again only with the same
    values). ``sim.add_collider(...)`` is ``attach(sim).add_collider(...)``.

    * ``dhat`` [m]: barrier distance of the implicit (IPC) steps; default 1e-3 of the body's
      bounding-box diagonal (at least 1e-4 of its smallest spring or edge).
    * ``friction`` (Coulomb mu of the implicit steps), ``friction_velocity``, ``tol``,
      ``max_newton``, ``barrier_stiffness``: as :class:`Scene`.
    * ``triangles`` (mass-spring only): the collision surface (cloth triangles), so that
      collider edges cannot slip between its vertices.
    """
    from kinema import fem, massspring

    if not isinstance(sim, (fem.Body, massspring.System)):
        raise ValueError(f"sim: expected a km.fem.Body or km.massspring.System, got {type(sim).__name__}")
    options = dict(dhat=dhat, friction=friction, friction_velocity=friction_velocity, tol=tol,
                   max_newton=max_newton, triangles=triangles, barrier_stiffness=barrier_stiffness)
    if sim.contact is None:
        # every option checked now, as the implicit steps' Scene will take it
        Scene(dhat=1e-3 if dhat is None else dhat, friction=friction, friction_velocity=friction_velocity, tol=tol,
              max_newton=max_newton, barrier_stiffness=barrier_stiffness)
        if triangles is not None:
            if isinstance(sim, fem.Body):
                raise ValueError("triangles: a km.fem.Body collides with its boundary surface; do not pass triangles")
            options["triangles"] = _indices(triangles, "triangles", 3)
        sim.contact = BodyContact(sim, **options)
    else:
        given = {k: v for k, v in options.items() if v is not None and not _same(v, sim.contact.options[k])}
        defaults = dict(friction=0.0, friction_velocity=1e-3, tol=1e-2, max_newton=500)
        given = {k: v for k, v in given.items() if not (k in defaults and _same(v, defaults[k]))}
        if given:
            name = sorted(given)[0]
            raise ValueError(f"{name}: the contact options of this body are already set "
                             f"({name}={sim.contact.options[name]!r}); pass them on the first attach")
    return sim.contact


def _same(a, b):
    try:
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    except (TypeError, ValueError):
        return a is b


class BodyContact:
    """Colliders of one ``km.fem.Body`` or ``km.massspring.System`` (see :func:`attach`).

    * Implicit steps (``integrator="implicit"``) are solved as one :class:`Scene` holding the
      body and its colliders: implicit Euler with IPC (barrier, lagged friction, CCD-clamped
      Newton), intersection-free by construction. The body's own Newton options (``tol``,
      ``linear_solver`` of km.fem; ``linear_solver``, ``cg_tol`` of km.massspring) do not
      apply there; the scene's ``tol`` does. km.massspring needs ``beta=1``. 3D only.
    * Symplectic steps (``integrator="symplectic"``) take the body's own explicit step and
      then project: every vertex inside a collider is moved to the nearest point of its
      surface, its normal velocity relative to the collider is removed (perfectly inelastic)
      and its tangential one reduced by ``friction`` times the removed normal speed (Coulomb,
      never reversed). Projection adds no stiffness, so the stable step is the body's own
      ``explicit_dt_limit``, checked as the body's step checks it (once per call: a RuntimeWarning
      above it, ValueError above ``unstable_dt``); what it adds is a tunnelling limit, checked
      before each step:
      a vertex must not travel more than half the thickness of the thinnest collider in one
      step (``max|v| dt + |g| dt^2 <= min thickness / 2``; planes are infinitely thick), or
      the step raises ValueError naming dt. Planes, boxes and spheres, in 2D and 3D (a 2D
      box or sphere is a rectangle or disc in the body's plane); mesh colliders need the
      implicit steps.
    """

    def __init__(self, sim, **options):
        self.sim = sim
        self.options = options
        self.colliders = []  # (shape, options) as given
        self._scene = None
        self._specs = None

    @property
    def dim(self):
        return self.sim.x.shape[1]

    def add_collider(self, shape, *, friction=None, **options):
        """Adds a collider: ``shape`` and its options as :meth:`Scene.add_collider` (in 2D:
        "plane" with 2D ``point`` and ``normal``, "box" with 2D ``lower``/``upper``, "sphere"
        with a 2D ``center``; ``velocity`` (d,) moves it). ``friction``: this collider's
        Coulomb mu, for the symplectic projection and the implicit steps alike (default: the
        body's ``friction``). Returns the number of colliders."""
        shape = choice(shape, "shape", ("plane", "box", "sphere", "mesh"))
        mu = self.options["friction"] if friction is None else non_negative(friction, "friction")
        if self.dim == 2:
            unknown = set(options) - {"point", "normal", "lower", "upper", "center", "radius", "velocity"}
            if unknown or shape == "mesh":
                what = "mesh" if shape == "mesh" else sorted(unknown)[0]
                raise ValueError(f"{what}: a 2D body takes plane, box and sphere colliders with point, normal, "
                                 "lower, upper, center, radius and velocity")
        else:  # every option checked now, as the implicit steps' Scene will take it
            Scene().add_collider(shape, **options)
        if shape != "mesh" and not set(options) - _PROJECTED:  # and as the symplectic steps will
            _projection_spec(shape, options, mu, self.dim)
        self.colliders.append((shape, dict(options), mu))
        self._scene = None
        self._specs = None
        return len(self.colliders)

    # ------------------------------------------------------------------ implicit: one IPC scene

    def scene(self) -> Scene:
        """The :class:`Scene` behind the implicit steps (rebuilt when a collider is added)."""
        if self._scene is None:
            if self.dim != 3:
                raise ValueError("integrator: implicit contact (IPC) is 3D only; a 2D body takes "
                                 "integrator='symplectic' with colliders")
            o = self.options
            x = _points(self.sim.x, "x") if self.dim == 3 else self.sim.x
            diag = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
            dhat = o["dhat"] if o["dhat"] is not None else 1e-3 * max(diag, 1e-9)
            scene = Scene(gravity=None if not np.any(self._gravity()) else self._gravity(), dhat=dhat,
                          friction=o["friction"], friction_velocity=o["friction_velocity"], tol=o["tol"],
                          max_newton=o["max_newton"], barrier_stiffness=o["barrier_stiffness"])
            scene._core.time = self.sim.time
            scene.add_body(self.sim, triangles=o["triangles"])
            for shape, kw, mu in self.colliders:
                scene.add_collider(shape, friction=mu, **kw)
            self._scene = scene
        return self._scene

    def _gravity(self):
        g = self.sim._gravity if hasattr(self.sim, "_gravity") else self.sim.gravity
        return np.zeros(self.dim) if g is None or len(g) == 0 else np.asarray(g, float)

    def step(self, dt, integrator, steps=1, *, beta=1.0):
        """``steps`` steps of ``dt`` with contact; returns the last step's stats (a
        :class:`StepStats` for implicit steps, the body's own stats for symplectic ones, with
        ``contact_count`` and ``min_distance`` attributes of the projection added)."""
        dt = time_step(dt)
        integrator = choice(integrator, "integrator", ("implicit", "symplectic", "explicit"))
        stats = None
        if integrator == "implicit":
            if float(beta) != 1.0:
                raise ValueError(f"beta: implicit steps with colliders are backward Euler (beta = 1), got {beta}")
            if self._scene is not None and self._scene.time != self.sim.time:
                self._scene = None  # the body's time was set (a restored state): colliders re-placed
            scene = self.scene()
            for _ in range(steps):
                stats = scene.step(dt)
            return stats
        # the body's explicit limit, once for the call (its own step then skips it)
        self.sim._check_explicit_dt(dt, integrator)
        for _ in range(steps):
            stats = self._projected_step(dt, integrator)
        return stats

    # ------------------------------------------------------------------ symplectic: projection

    def _shapes(self):
        if self._specs is None:
            self._specs = [_projection_spec(shape, kw, mu, self.dim) for shape, kw, mu in self.colliders]
        return self._specs

    def _projected_step(self, dt, integrator):
        sim = self.sim
        specs = self._shapes()
        t0 = sim.time
        # Tunnelling limit: no vertex may cross half the thinnest collider in one step.
        thin = min(s["thickness"] for s in specs)
        if np.isfinite(thin):
            rel = max(float(np.abs(sim.v - s["velocity"]).max()) * np.sqrt(self.dim) for s in specs)
            travel = rel * dt + float(np.linalg.norm(self._gravity())) * dt * dt
            if travel > 0.5 * thin:
                raise ValueError(f"dt: {dt} lets a vertex travel {travel:.3g} m in one step, more than half the "
                                 f"thinnest collider ({thin:.3g} m): it could pass through; use dt <= "
                                 f"{0.5 * thin / max(travel / dt, 1e-300):.3g}")
        sim.contact, keep = None, sim.contact  # the body's own step, without this hook
        try:
            stats = sim._step(dt, None, integrator=integrator, check=False)  # checked in step()
        finally:
            sim.contact = keep
        x, v = sim.x, sim.v
        t1 = t0 + dt
        free = np.ones(len(x), bool)
        fixed = getattr(sim, "fixed", ())
        if len(fixed):
            free[np.asarray(fixed, np.int64)] = False
        count = 0
        dmin = np.inf
        for s in specs:
            shift = s["velocity"] * t1
            depth, normal = _signed_distance(s, x - shift)
            inside = (depth < 0) & free
            dmin = min(dmin, float(depth[free].min()) if free.any() else np.inf)
            if not inside.any():
                continue
            count += int(inside.sum())
            n = normal[inside]
            x[inside] -= depth[inside, None] * n
            vr = v[inside] - s["velocity"]
            vn = np.einsum("ij,ij->i", vr, n)
            approaching = vn < 0
            vt = vr - vn[:, None] * n
            speed = np.linalg.norm(vt, axis=1)
            scale = np.where(speed > 0, np.maximum(0.0, 1 - s["mu"] * np.abs(vn) / np.where(speed > 0, speed, 1)),
                             0.0)
            new = np.where(approaching[:, None], vt * scale[:, None], vr)
            v[inside] = new + s["velocity"]
        stats_contact = _ProjectionStats(stats, count, dmin)
        return stats_contact


_PROJECTED = {"velocity", "point", "normal", "lower", "upper", "center", "radius", "subdivisions"}


def _projection_spec(shape, kw, mu, d):
    """The checked description of one collider for the symplectic projection."""
    if shape == "mesh":
        raise ValueError("integrator: a mesh collider needs the implicit integrator (IPC)")
    extra = set(kw) - _PROJECTED
    if extra:
        raise ValueError(f"{sorted(extra)[0]}: symplectic steps move colliders by a constant "
                         "velocity only (motion and angular_velocity need the implicit integrator)")
    _required(shape, kw)
    vel = np.zeros(d) if kw.get("velocity") is None else _vecd(kw["velocity"], "velocity", d)
    spec = {"shape": shape, "mu": mu, "velocity": vel}
    if shape == "plane":
        n = _vecd(kw.get("normal", np.eye(d)[1]), "normal", d)
        if not n.any():
            raise ValueError("normal: expected a non-zero vector")
        n = n / np.abs(n).max()  # its norm is then representable
        spec.update(point=_vecd(kw.get("point", np.zeros(d)), "point", d), normal=n / np.linalg.norm(n),
                    thickness=np.inf)
    elif shape == "box":
        lo, hi = _vecd(kw["lower"], "lower", d), _vecd(kw["upper"], "upper", d)
        if not (hi > lo).all():
            raise ValueError("lower, upper: expected lower < upper on every axis")
        spec.update(lower=lo, upper=hi, thickness=float((hi - lo).min()))
    else:
        r = positive(kw["radius"], "radius")
        spec.update(center=_vecd(kw.get("center", np.zeros(d)), "center", d), radius=r, thickness=2 * r)
    return spec


class _ProjectionStats:
    """The body's step stats with the projection's ``contact_count`` (vertices projected) and
    ``min_distance`` (smallest signed distance [m] of a vertex to a collider before the
    projection: negative means it had entered one)."""

    def __init__(self, stats, count, dmin):
        self.stats, self.contact_count, self.min_distance = stats, count, dmin

    def __getattr__(self, name):
        return getattr(self.stats, name)

    def __repr__(self):
        return f"ProjectionStats(contact_count={self.contact_count}, min_distance={self.min_distance:.3g}, {self.stats!r})"


def _vecd(a, name, d):
    arr = as_float_array(a, name).reshape(-1)
    if arr.size != d or not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected {d} finite coordinates, got {np.asarray(a).tolist()!r}")
    return arr


def _signed_distance(spec, x):
    """Signed distance (n,) [m] of points to a collider (negative inside) and the outward
    normal (n, d) of the nearest surface point."""
    if spec["shape"] == "plane":
        n = spec["normal"]
        return (x - spec["point"]) @ n, np.broadcast_to(n, x.shape)
    if spec["shape"] == "sphere":
        r = x - spec["center"]
        dist = np.linalg.norm(r, axis=1)
        safe = np.where(dist > 0, dist, 1.0)
        n = np.where(dist[:, None] > 0, r / safe[:, None], np.eye(x.shape[1])[1])
        return dist - spec["radius"], n
    lo, hi = spec["lower"], spec["upper"]
    c, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(x - c) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    axis = q.argmax(axis=1)
    n = np.zeros_like(x)
    n[np.arange(len(x)), axis] = np.sign(x - c)[np.arange(len(x)), axis]
    n[n.sum(axis=1) == 0, axis[n.sum(axis=1) == 0]] = 1  # a point on a symmetry plane
    return outside + inside, n
