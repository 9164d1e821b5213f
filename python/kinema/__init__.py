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
]


def set_num_threads(n: int) -> None:
    """Sets the number of OpenMP threads kinema's kernels use, for the whole process: a call
    made from any Python thread (a worker of a thread pool included) uses this count.
    n: an integer in [1, max(64, 4 x the number of processors)]; more raises ValueError."""
    from kinema._checks import integer
    _core.set_num_threads(integer(n, "n", low=1, high=_core.max_num_threads()))


def get_num_threads() -> int:
    """The number of OpenMP threads kinema's kernels use (the last set_num_threads, else
    OpenMP's default: OMP_NUM_THREADS or the number of processors)."""
    return _core.get_num_threads()


def build_info() -> dict:
    """How this kinema was built: compiler, flags, OpenMP, Eigen, CHOLMOD and the BLAS in use."""
    info = dict(_core.build_info())
    info["threads"] = str(get_num_threads())
    return info
