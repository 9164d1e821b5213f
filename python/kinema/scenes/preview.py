"""A fast preview renderer in NumPy: colour-mapped grid fields, particle splats and flat-shaded
triangle meshes seen by an orthographic camera. Images are (H, W, 3) uint8, row 0 at the top.

The camera looks at the plane of two world axes ``axes = (a, b)`` (a to the right, b up) over
the window ``[lower, upper]`` of those axes; in 3D the third axis gives the depth, the viewer
sitting on the side of e_a x e_b.
"""

from __future__ import annotations

import numpy as np

BACKGROUND = np.array([24, 24, 28], np.uint8)


def colormap(values, name="viridis", vmin=None, vmax=None):
    """(..., 3) uint8 colours of ``values`` through a matplotlib colormap (NaN -> background)."""
    import matplotlib

    v = np.asarray(values, dtype=float)
    lo = np.nanmin(v) if vmin is None else vmin
    hi = np.nanmax(v) if vmax is None else vmax
    t = np.clip((v - lo) / (hi - lo), 0, 1) if hi > lo else np.zeros_like(v)
    lut = (matplotlib.colormaps[name](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    rgb = lut[np.nan_to_num(t * 255).astype(np.int64)]
    rgb[np.isnan(v)] = BACKGROUND
    return rgb


def field_image(field, *, cmap="viridis", vmin=None, vmax=None, mask=None, width=None):
    """A 2D cell field [i, j] (x right, y up) as an image, each cell scaled up to whole pixels
    so that the image is at least ``width`` pixels wide; ``mask`` cells are drawn grey."""
    rgb = colormap(field, cmap, vmin, vmax)
    if mask is not None:
        rgb[np.asarray(mask, bool)] = (110, 110, 115)
    img = rgb.transpose(1, 0, 2)[::-1]  # rows: y from the top
    scale = max(1, -(-width // field.shape[0])) if width else 1
    return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)


class Camera:
    """Orthographic projection of world points to pixels (see the module docstring)."""

    def __init__(self, axes, lower, upper, width):
        self.axes = tuple(axes)
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        extent = self.upper - self.lower
        self.scale = width / extent[0]  # pixels per metre
        self.width = int(width)
        self.height = max(1, int(round(extent[1] * self.scale)))

    def project(self, x):
        """Pixel columns, rows (floats) and depth towards the viewer of the (n, d) points."""
        x = np.asarray(x, float)
        a, b = self.axes
        col = (x[:, a] - self.lower[0]) * self.scale
        row = (self.upper[1] - x[:, b]) * self.scale
        if x.shape[1] == 3:
            toward = np.cross(np.eye(3)[a], np.eye(3)[b])
            depth = x @ toward
        else:
            depth = np.zeros(len(x))
        return col, row, depth

    def canvas(self):
        return np.broadcast_to(BACKGROUND, (self.height, self.width, 3)).copy()


def splat(camera, points, colors, radius_px=2.0, image=None):
    """Particles as shaded discs, nearest in front (z-buffered): (n, d) points, (n, 3) colours."""
    img = camera.canvas() if image is None else image
    col, row, depth = camera.project(points)
    r = max(float(radius_px), 0.5)
    k = int(np.ceil(r))
    dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
    inside = dx**2 + dy**2 <= r * r
    dx, dy = dx[inside], dy[inside]
    # Sphere shading: brightness from the normal's component towards the viewer.
    shade = np.sqrt(np.clip(1 - (dx**2 + dy**2) / (r * r + 1), 0, 1)) * 0.6 + 0.4
    ci = np.floor(col).astype(np.int64)[:, None] + dx
    ri = np.floor(row).astype(np.int64)[:, None] + dy
    ok = (ci >= 0) & (ci < camera.width) & (ri >= 0) & (ri < camera.height)
    pix = (ri * camera.width + ci)[ok]
    owner = np.broadcast_to(np.arange(len(col))[:, None], ci.shape)[ok]
    zbuf = np.full(camera.width * camera.height, -np.inf)
    np.maximum.at(zbuf, pix, depth[owner])
    # Of the nearest particles at a pixel the one with the largest index wins (deterministic).
    win = np.full(zbuf.shape, -1)
    front = depth[owner] == zbuf[pix]
    np.maximum.at(win, pix[front], owner[front])
    flat = img.reshape(-1, 3)
    sel = front & (win[pix] == owner)
    s = np.broadcast_to(shade, ci.shape)[ok][sel]
    flat[pix[sel]] = (np.asarray(colors, float)[owner[sel]] * s[:, None]).astype(np.uint8)
    return img


def triangles(camera, points, tris, color=(90, 160, 230), image=None):
    """A triangle mesh, flat shaded by |normal . view|. Each pixel shows the triangle whose
    centroid is nearest the viewer (z-buffered per triangle; ties: the largest index).
    Triangles are rasterised in batches of similar bounding-box size, all in NumPy."""
    img = camera.canvas() if image is None else image
    col, row, depth = camera.project(points)
    tris = np.asarray(tris, np.int64)
    p = np.asarray(points, float)
    if p.shape[1] == 2:
        p = np.hstack([p, np.zeros((len(p), 1))])
    a, b = camera.axes
    toward = np.cross(np.eye(3)[a], np.eye(3)[b])
    n = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    light = np.abs(n @ toward) / np.where(norm > 0, norm, 1)
    xs, ys = col[tris], row[tris]  # (T, 3) pixel coordinates of the corners
    tri_depth = depth[tris].mean(axis=1)
    c0, r0 = np.floor(xs.min(axis=1)).astype(np.int64), np.floor(ys.min(axis=1)).astype(np.int64)
    extent = np.maximum(np.ceil(xs.max(axis=1)) - c0, np.ceil(ys.max(axis=1)) - r0).astype(np.int64) + 1
    det = (xs[:, 1] - xs[:, 0]) * (ys[:, 2] - ys[:, 0]) - (xs[:, 2] - xs[:, 0]) * (ys[:, 1] - ys[:, 0])
    W, H = camera.width, camera.height
    zbuf = np.full(W * H, -np.inf)
    hits_pix, hits_tri = [], []
    box = 4
    while True:
        batch = np.flatnonzero((extent <= box) & (extent > box // 2 if box > 4 else True) & (det != 0))
        for chunk in np.array_split(batch, max(1, len(batch) * box * box // 2_000_000 + 1)):
            if len(chunk) == 0:
                continue
            dy, dx = np.divmod(np.arange(box * box), box)
            X = c0[chunk, None] + dx + 0.5
            Y = r0[chunk, None] + dy + 0.5
            x0, y0 = xs[chunk, 0, None], ys[chunk, 0, None]
            d = det[chunk, None]
            w1 = ((X - x0) * (ys[chunk, 2, None] - y0) - (xs[chunk, 2, None] - x0) * (Y - y0)) / d
            w2 = ((xs[chunk, 1, None] - x0) * (Y - y0) - (X - x0) * (ys[chunk, 1, None] - y0)) / d
            ci, ri = X.astype(np.int64), Y.astype(np.int64)
            ok = (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1) & (ci >= 0) & (ci < W) & (ri >= 0) & (ri < H)
            pix = (ri * W + ci)[ok]
            tri = np.broadcast_to(chunk[:, None], ok.shape)[ok]
            np.maximum.at(zbuf, pix, tri_depth[tri])
            hits_pix.append(pix)
            hits_tri.append(tri)
        if box >= extent.max(initial=0):
            break
        box *= 2
    if not hits_pix:
        return img
    pix, tri = np.concatenate(hits_pix), np.concatenate(hits_tri)
    front = tri_depth[tri] == zbuf[pix]
    owner = np.full(W * H, -1)
    np.maximum.at(owner, pix[front], tri[front])
    shown = np.flatnonzero(owner >= 0)
    shade = 0.35 + 0.65 * light[owner[shown]]
    img.reshape(-1, 3)[shown] = (np.asarray(color, float) * shade[:, None]).astype(np.uint8)
    return img


def boundary_faces(tets):
    """The triangles on the surface of a tetrahedral mesh (faces used by one tet only)."""
    tets = np.asarray(tets, np.int64)
    faces = np.concatenate([tets[:, [0, 2, 1]], tets[:, [0, 1, 3]], tets[:, [0, 3, 2]], tets[:, [1, 2, 3]]])
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]
