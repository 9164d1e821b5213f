"""Rendering: a Monte Carlo path tracer and a fast preview for particles, meshes and planes.

    scene = km.render.Scene()
    scene.add_plane((0, 0, 0), (0, 1, 0), km.render.lambertian(0.7))
    scene.add_spheres(x, 0.01, km.render.dielectric(1.5))     # particles: (n, 3) centres
    scene.add_mesh(vertices, triangles, km.render.metal(0.9, fuzz=0.1))
    cam = km.render.Camera((0, 1, 3), (0, 0.3, 0), vfov=40, width=640, height=480)
    image = scene.render(cam, spp=64)                           # (480, 640, 3) linear radiance
    km.render.to_png(image, "frame.png")

The path tracer (C++, OpenMP) estimates the rendering equation with BSDF-sampled paths:
cosine-weighted Lambertian bounces, Shirley's fuzzy metal, clear glass choosing Fresnel-Schlick
reflection or Snell refraction, emitters and a uniform or gradient sky; jittered sub-pixel
samples for anti-aliasing and Russian roulette after ``roulette_depth`` bounces (unbiased: the
surviving throughput is divided by the survival probability). Spheres and triangles share one
bounding volume hierarchy (binned SAH); planes are infinite. Images are bitwise identical for
any thread count (each sample of each pixel has its own random stream from ``seed``).

:meth:`Scene.preview` (and :func:`preview`) is a z-buffered sphere splatter and triangle
rasteriser with Blinn-Phong shading and optional soft shadows for the frames of long simulations (milliseconds at 100k
particles); it sees exactly what the path tracer's primary rays through the pixel centres see.

Units: lengths in the scene's unit; radiance in any linear unit (the image is in the sky's and
emitters' units). Colours are RGB triples or a scalar for grey. Image rows run top to bottom.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinema import _core
from kinema._checks import as_float_array, non_negative, positive, positive_int, simulation_object

__all__ = [
    "Material",
    "lambertian",
    "metal",
    "dielectric",
    "emissive",
    "Camera",
    "Scene",
    "preview",
    "splat_spheres",
    "tone_map",
    "to_png",
]

#: The default sky: Shirley's gradient from white at the nadir to light blue at the zenith.
DEFAULT_SKY = ((1.0, 1.0, 1.0), (0.5, 0.7, 1.0))


def _rgb(x, name, *, upper=math.inf):
    a = as_float_array(x, name)
    if np.ndim(x) == 0:  # as_float_array makes scalars 1-d
        a = np.full(3, float(a[0]))
    if a.shape != (3,):
        raise ValueError(f"{name}: expected a scalar or an RGB triple, got shape {a.shape}")
    if a.min() < 0 or a.max() > upper:
        raise ValueError(f"{name}: expected components in [0, {upper}], got {tuple(a)}")
    return tuple(float(v) for v in a)


def _vec3(x, name):
    a = as_float_array(x, name)
    if a.shape != (3,):
        raise ValueError(f"{name}: expected 3 coordinates, got shape {a.shape}")
    return tuple(float(v) for v in a)


# ------------------------------------------------------------------ materials


@dataclass(frozen=True)
class Material:
    """A surface material; build one with lambertian, metal, dielectric or emissive.

    kind: "lambertian", "metal" or "dielectric". albedo: RGB reflectance in [0, 1].
    fuzz: metal roughness in [0, 1]. ior: index of refraction (> 0) of a dielectric.
    emission: RGB radiance emitted from both faces (>= 0). absorption: a dielectric's RGB
    Beer-Lambert coefficient [1/length] (>= 0; light crossing a length t inside keeps exp(-a t)).
    """

    kind: str
    albedo: tuple = (0.5, 0.5, 0.5)
    fuzz: float = 0.0
    ior: float = 1.5
    emission: tuple = (0.0, 0.0, 0.0)
    absorption: tuple = (0.0, 0.0, 0.0)


def lambertian(albedo=0.5, *, emission=0.0) -> Material:
    """Ideal diffuse reflector, f = albedo / pi (albedo in [0, 1]); may also emit ``emission``."""
    return Material("lambertian", _rgb(albedo, "albedo", upper=1.0),
                    emission=_rgb(emission, "emission"))


def metal(albedo=0.9, fuzz=0.0) -> Material:
    """Mirror reflection times ``albedo``, blurred by ``fuzz`` in [0, 1] (Shirley's fuzzy metal:
    the mirror direction plus fuzz times a random point of the unit ball; directions pushed
    below the surface are absorbed). With fuzz 0 and albedo 1 no energy is lost."""
    f = non_negative(fuzz, "fuzz")
    if f > 1:
        raise ValueError(f"fuzz: expected a number in [0, 1], got {f}")
    return Material("metal", _rgb(albedo, "albedo", upper=1.0), fuzz=f)


def dielectric(ior=1.5, *, absorption=0.0) -> Material:
    """Clear glass of refractive index ``ior`` (> 0) in vacuum: reflects with the Fresnel-Schlick
    probability R, refracts by Snell's law with 1 - R, reflects totally beyond the critical angle
    (R + T = 1 at the interface). absorption: RGB (or scalar) Beer-Lambert coefficient
    [1/length] >= 0 inside (0: clear; water's blue-green: larger in red than in blue)."""
    return Material("dielectric", (1.0, 1.0, 1.0), ior=positive(ior, "ior"),
                    absorption=_rgb(absorption, "absorption"))


def emissive(radiance) -> Material:
    """A black emitter of RGB ``radiance`` (>= 0) from both faces: a light source."""
    return Material("lambertian", (0.0, 0.0, 0.0), emission=_rgb(radiance, "radiance"))


# ------------------------------------------------------------------ camera


# Images up to 2^25 pixels (768 MiB of float64 RGB) and 2^16 pixels a side; up to 2^20 samples per
# pixel and 2^16 bounces (beyond, a render would not end in any useful time).
MAX_SIDE, MAX_PIXELS, MAX_SPP, MAX_DEPTH = 2**16, 2**25, 2**20, 2**16


class Camera:
    """Pinhole camera at ``look_from`` looking at ``look_at``.

    up: the direction that appears upwards (not parallel to the view). vfov: full vertical field
    of view in degrees, in (0, 180). width, height: image size in pixels (>= 1).
    """

    def __init__(self, look_from, look_at, up=(0.0, 1.0, 0.0), vfov=40.0, *, width=640, height=480):
        self.look_from = _vec3(look_from, "look_from")
        self.look_at = _vec3(look_at, "look_at")
        self.up = _vec3(up, "up")
        self.vfov = positive(vfov, "vfov")
        if self.vfov >= 180:
            raise ValueError(f"vfov: expected degrees in (0, 180), got {self.vfov}")
        self.width = positive_int(width, "width", high=MAX_SIDE)
        self.height = positive_int(height, "height", high=MAX_SIDE)
        if self.width * self.height > MAX_PIXELS:
            raise ValueError(f"width, height: {self.width} x {self.height} is more than the {MAX_PIXELS} "
                             f"pixels supported ({self.width * self.height * 24 / 2**30:.1f} GiB of float64 RGB)")
        view = np.subtract(self.look_at, self.look_from)
        if not np.any(view):
            raise ValueError("look_at: must differ from look_from")
        if np.linalg.norm(np.cross(view / np.linalg.norm(view), self.up)) < 1e-9 * max(
                np.linalg.norm(self.up), 1e-300):
            raise ValueError("up: must not be zero or parallel to the viewing direction")

    def _args(self):
        return (self.look_from, self.look_at, self.up, self.vfov, self.width, self.height)

    def __repr__(self):
        return (f"Camera(look_from={self.look_from}, look_at={self.look_at}, up={self.up}, "
                f"vfov={self.vfov}, width={self.width}, height={self.height})")


def _sky(sky):
    """(bottom, top) RGB radiances from a scalar, an RGB triple or a (2, 3) pair."""
    a = as_float_array(sky, "sky")
    if np.ndim(sky) == 0 or a.shape == (3,):
        rgb = _rgb(sky, "sky")
        return rgb, rgb
    if a.shape != (2, 3):
        raise ValueError("sky: expected a radiance, an RGB triple or a (bottom, top) pair of "
                         f"triples, got shape {a.shape}")
    return _rgb(a[0], "sky[0] (bottom)"), _rgb(a[1], "sky[1] (top)")


# ------------------------------------------------------------------ scene


@simulation_object
class Scene:
    """Spheres, triangle meshes and infinite planes with their materials.

    Geometry is copied into the scene when added. Primitive ids (returned by ``intersect``,
    ``primary_hits`` and ``preview(..., return_ids=True)``) number the spheres first, then the
    triangles, then the planes, each in the order added.
    """

    def __init__(self):
        self._scene = _core.render.Scene()
        self._materials: dict = {}
        #: Statistics of the last render: rays, seconds, bvh_seconds, bvh_nodes, bvh_depth.
        self.last_stats: dict = {}

    def _material(self, material):
        if not isinstance(material, Material):
            raise ValueError("material: expected a km.render.Material (lambertian, metal, "
                             f"dielectric or emissive), got {material!r}")
        if material not in self._materials:
            self._materials[material] = self._scene.add_material(
                material.kind, material.albedo, material.fuzz, material.ior, material.emission,
                material.absorption)
        return self._materials[material]

    @property
    def sphere_count(self) -> int:
        return self._scene.sphere_count

    @property
    def triangle_count(self) -> int:
        return self._scene.triangle_count

    @property
    def plane_count(self) -> int:
        return self._scene.plane_count

    def add_spheres(self, centers, radii, material) -> None:
        """centers: (n, 3) sphere centres; radii: (n,) radii > 0, or one radius for all."""
        c = as_float_array(centers, "centers", ndim=(1, 2))
        if c.ndim == 1:
            c = c.reshape(1, -1)
        if c.shape[1] != 3:
            raise ValueError(f"centers: expected shape (n, 3), got {c.shape}")
        r = as_float_array(radii, "radii")
        if np.ndim(radii) == 0:
            r = np.full(c.shape[0], float(r[0]))
        if r.shape != (c.shape[0],):
            raise ValueError(f"radii: expected a scalar or shape ({c.shape[0]},), got {r.shape}")
        if r.size and r.min() <= 0:
            raise ValueError(f"radii: expected radii > 0, got {r.min()}")
        self._scene.add_spheres(c, r, self._material(material))

    def add_mesh(self, vertices, triangles, material) -> None:
        """vertices: (m, 3) positions; triangles: (k, 3) vertex indices in [0, m)."""
        v = as_float_array(vertices, "vertices", ndim=2)
        if v.shape[1] != 3:
            raise ValueError(f"vertices: expected shape (m, 3), got {v.shape}")
        t = np.asarray(triangles)
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"triangles: expected shape (k, 3), got {t.shape}")
        if t.size and not np.issubdtype(t.dtype, np.integer):
            raise ValueError(f"triangles: expected integer vertex indices, got dtype {t.dtype}")
        t = np.ascontiguousarray(t, dtype=np.int64)
        if t.size and (t.min() < 0 or t.max() >= v.shape[0]):
            raise ValueError(f"triangles: vertex indices must lie in [0, {v.shape[0]}), got "
                             f"[{t.min()}, {t.max()}]")
        self._scene.add_mesh(v, t, self._material(material))

    def add_plane(self, point, normal, material) -> None:
        """The infinite plane through ``point`` with ``normal`` (non-zero, any length)."""
        n = _vec3(normal, "normal")
        if not any(n):
            raise ValueError("normal: expected a non-zero vector")
        self._scene.add_plane(_vec3(point, "point"), n, self._material(material))

    def render(self, camera, *, spp=64, max_depth=16, seed=0, sky=DEFAULT_SKY,
               russian_roulette=True, roulette_depth=3, return_variance=False):
        """Path-traced image, (height, width, 3) float64 linear radiance (rows top to bottom).

        spp: samples per pixel (>= 1). max_depth: bounces after which a path is cut (>= 1).
        seed: integer in [0, 2**64); the same seed gives the same image on any thread count.
        sky: radiance of rays leaving the scene: a scalar or RGB (uniform), or (bottom, top)
        RGB pair, L(d) = bottom + (top - bottom)(1 + d_y) / 2 for the unit direction d.
        russian_roulette, roulette_depth: terminate paths at random from that bounce on,
        surviving with probability min(1, max throughput) (unbiased).
        return_variance: also return the estimated variance of each pixel's mean (spp >= 2),
        for error bars: (image, variance), both (height, width, 3).
        """
        cam = _camera(camera)
        spp = positive_int(spp, "spp", high=MAX_SPP)
        max_depth = positive_int(max_depth, "max_depth", high=MAX_DEPTH)
        roulette_depth = positive_int(roulette_depth, "roulette_depth", high=MAX_DEPTH)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
            raise ValueError(f"seed: expected an integer in [0, 2**64), got {seed!r}")
        if return_variance and spp < 2:
            raise ValueError("spp: return_variance needs >= 2 samples per pixel")
        bottom, top = _sky(sky)
        if not russian_roulette:
            roulette_depth = max_depth
        image, var, stats = self._scene.render(*cam._args(), bottom, top, spp, max_depth,
                                               roulette_depth, int(seed), bool(return_variance))
        self.last_stats = dict(stats)
        return (image, var) if return_variance else image

    def preview(self, camera, *, sky=DEFAULT_SKY, light=(0.3, 1.0, 0.5), ambient=0.25,
                specular=0.0, shininess=32.0, shadows=0, light_radius=0.05, return_ids=False):
        """Fast shaded view: (height, width, 3) float64 linear radiance, Blinn-Phong shading
        (Blinn 1977) under a distant light on surfaces, the sky elsewhere:

            albedo (ambient + (1 - ambient) V max(0, n . l)) + specular V max(0, n . h)^shininess + emission

        with h the unit half vector of l and the direction to the eye, and V the visible
        fraction of the light (1 without shadows). Glass is drawn as water: a blue-green body
        colour so lit, mixed with the sky it reflects by Schlick's Fresnel factor.

        light: direction towards a distant light. ambient: in [0, 1]. specular: k_s >= 0 (0, the
        default, is Lambert's law alone). shininess: the exponent (> 0). shadows: rays per pixel
        towards the light (0: none); light_radius: the light's angular radius [rad] in [0, 1.5),
        the softness of the shadows' edges.
        return_ids: also return the (height, width) int64 ids of the visible primitives (-1 for
        the sky) and the (height, width) distances along the pixel-centre rays (inf on a miss).
        """
        cam = _camera(camera)
        bottom, top = _sky(sky)
        lv = _vec3(light, "light")
        if not any(lv):
            raise ValueError("light: expected a non-zero direction")
        a = non_negative(ambient, "ambient")
        if a > 1:
            raise ValueError(f"ambient: expected a number in [0, 1], got {a}")
        if isinstance(shadows, bool) or not isinstance(shadows, (int, np.integer)) or shadows < 0:
            raise ValueError(f"shadows: expected an integer >= 0 (rays per pixel), got {shadows!r}")
        image, ids, depth = self._scene.preview(*cam._args(), bottom, top, lv, a, non_negative(specular, "specular"),
                                                positive(shininess, "shininess"), int(shadows),
                                                non_negative(light_radius, "light_radius"))
        return (image, ids, depth) if return_ids else image

    def primary_hits(self, camera):
        """(height, width) int64 ids of the primitives the path tracer's rays through the pixel
        centres hit first (-1 for none), found through the BVH."""
        return self._scene.primary_hits(*_camera(camera)._args())

    def intersect(self, origins, directions, *, brute_force=False):
        """Closest hits of rays: origins, directions (n, 3) (directions are normalised).

        Returns (t, ids): (n,) distances (inf on a miss) and (n,) primitive ids (-1 on a miss).
        brute_force: test every primitive instead of traversing the BVH (the reference).
        """
        o = as_float_array(origins, "origins", ndim=2)
        if o.shape[1] != 3:
            raise ValueError(f"origins: expected shape (n, 3), got {o.shape}")
        d = as_float_array(directions, "directions", ndim=2)
        if d.shape != o.shape:
            raise ValueError(f"directions: expected shape {o.shape}, got {d.shape}")
        norm = np.linalg.norm(d, axis=1)
        if norm.size and norm.min() == 0:
            raise ValueError("directions: contains a zero vector")
        d = np.ascontiguousarray(d / norm[:, None])
        return self._scene.intersect(o, d, bool(brute_force))


def _camera(camera):
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a km.render.Camera, got {camera!r}")
    return camera


def preview(camera, *, centers=None, radii=None, vertices=None, triangles=None,
            material=None, mesh_material=None, floor=None, sky=DEFAULT_SKY,
            light=(0.3, 1.0, 0.5), ambient=0.25):
    """One-call preview of a simulation frame: particles and/or a mesh, optionally a floor.

    centers, radii: (n, 3) particle positions and their radii (scalar or (n,)).
    vertices, triangles: a triangle mesh. material, mesh_material: their materials (default:
    light grey Lambertian). floor: None or the height y of a grey floor plane.
    Returns the (height, width, 3) image of :meth:`Scene.preview`.
    """
    scene = Scene()
    grey = lambertian(0.7)
    if centers is not None:
        if radii is None:
            raise ValueError("radii: needed with centers")
        scene.add_spheres(centers, radii, material or grey)
    if vertices is not None or triangles is not None:
        if vertices is None or triangles is None:
            raise ValueError("vertices, triangles: give both or neither")
        scene.add_mesh(vertices, triangles, mesh_material or grey)
    if floor is not None:
        scene.add_plane((0.0, float(floor), 0.0), (0.0, 1.0, 0.0), lambertian(0.5))
    return scene.preview(camera, sky=sky, light=light, ambient=ambient)


# ------------------------------------------------------------------ output


def splat_spheres(camera, centers, radii):
    """What a camera sees of many spheres, for a live view: per pixel the distance to the first
    sphere along the pixel-centre ray, its unit outward normal there, and which sphere it is.

    camera: a :class:`Camera`. centers: (n, 3). radii: one radius > 0 for all, or (n,).
    Returns (depth, normals, ids, hits): float32 (height, width) and (height, width, 3), int32
    (height, width), with depth inf, normals 0 and ids -1 where no sphere is hit, and the number
    of pixels hit. The same projection and ray/sphere test as :meth:`Scene.preview` (so the same
    visible sphere as the path tracer's primary hits), without shading: cheap enough to redraw
    1e5 particles many times a second on a CPU. Colour a pixel by indexing with ``ids``.
    """
    cam = _camera(camera)
    c = as_float_array(centers, "centers", ndim=2)
    if c.shape[1] != 3:
        raise ValueError(f"centers: expected shape (n, 3), got {c.shape}")
    r = as_float_array(radii, "radii")
    if np.ndim(radii) != 0 and r.shape != (c.shape[0],):
        raise ValueError(f"radii: expected a scalar or shape ({c.shape[0]},), got {r.shape}")
    if r.size and not r.min() > 0:
        raise ValueError(f"radii: expected radii > 0, got {r.min()}")
    return _core.render.splat_spheres(c, r.reshape(-1), *cam._args())


def tone_map(image, *, exposure=1.0, gamma=2.2):
    """Linear radiance (h, w, 3) or (h, w) to 8-bit display values: clip((exposure v)^(1/gamma))."""
    a = as_float_array(image, "image", ndim=(2, 3))
    if a.ndim == 3 and a.shape[2] != 3:
        raise ValueError(f"image: expected shape (h, w, 3) or (h, w), got {a.shape}")
    if a.size and a.min() < 0:
        raise ValueError(f"image: radiance must be >= 0, got {a.min()}")
    e = positive(exposure, "exposure")
    g = positive(gamma, "gamma")
    v = np.clip((e * a) ** (1.0 / g), 0.0, 1.0)
    return np.round(255.0 * v).astype(np.uint8)


def to_png(image, path, *, exposure=1.0, gamma=2.2):
    """Tone-maps ``image`` (see :func:`tone_map`) and writes it as a PNG at ``path``, atomically
    (a temporary file renamed into place). Needs matplotlib (``pip install kinema[demo]``).
    Returns the path."""
    pixels = tone_map(image, exposure=exposure, gamma=gamma)
    try:
        from matplotlib import image as mpl_image
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("km.render.to_png needs matplotlib (pip install kinema[demo])") from exc
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[:, :, None], 3, axis=2)
    mpl_image.imsave(tmp, pixels, format="png")
    tmp.replace(path)
    return path
