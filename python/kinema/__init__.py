"""kinema: fast, verified physics simulation (C++/OpenMP core, Python interface).

    import kinema as km
    u, info = km.poisson.solve(f, h=1/256)

See README.md for an overview and API.md for the public contract.
"""

from kinema import _core
from kinema._info import SolveInfo
from kinema.errors import (
    ConvergenceError,
    DivergenceError,
    KinemaError,
    NotPositiveDefiniteError,
    StabilityError,
)
from kinema import diffusion, fem, fmm, grid, massspring, poisson, render, sparse, sph, vortex
from kinema.scenes import Scene, SceneError
from kinema import surface, viewer
from kinema.notebook import show

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "build_info",
    "get_num_threads",
    "set_num_threads",
    "SolveInfo",
    "KinemaError",
    "DivergenceError",
    "ConvergenceError",
    "StabilityError",
    "NotPositiveDefiniteError",
    "sparse",
    "poisson",
    "diffusion",
    "fmm",
    "vortex",
    "grid",
    "massspring",
    "fem",
    "sph",
    "render",
    "Scene",
    "SceneError",
    "surface",
    "viewer",
    "show",
]


def set_num_threads(n: int) -> None:
    """Sets the number of OpenMP threads kinema's kernels use (n >= 1)."""
    if isinstance(n, bool) or not isinstance(n, int):
        raise ValueError(f"n: expected an integer thread count >= 1, got {n!r}")
    _core.set_num_threads(n)


def get_num_threads() -> int:
    """The number of OpenMP threads kinema's kernels use."""
    return _core.get_num_threads()


def build_info() -> dict:
    """How this kinema was built: compiler, flags, OpenMP, Eigen, CHOLMOD and the BLAS in use."""
    info = dict(_core.build_info())
    info["threads"] = str(get_num_threads())
    return info
