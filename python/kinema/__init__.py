"""kinema: fast, verified physics simulation (C++/OpenMP core, Python interface).

    import kinema as km
    u, info = km.poisson.solve(f, h=1/256)

The user guide and API reference: docs/ in the source repository (``bash scripts/docs.sh``
builds them into HTML), or each function's docstring (``help(km.sph.Fluid)``).
"""

import os as _os

# OpenMP's waiting policy is read once, when the runtime starts (at the import of _core below).
# libgomp's default lets an idle thread spin ~3 ms before it sleeps: on a machine where another
# process keeps a core busy that spinning starves the thread it waits for, and a CG solve took
# 60x longer. A short bounded spin keeps most of the quiet-machine speed and the loaded-machine
# speed (bench/common/omp_wait_policy.py, bench/RESULTS.md). A user's own setting of either variable
# wins; this has no effect when another library started the OpenMP runtime first.
#: GOMP_SPINCOUNT kinema sets when the user set neither it nor OMP_WAIT_POLICY.
DEFAULT_GOMP_SPINCOUNT = "1000"
_OMP_USER = {k: _os.environ[k] for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY") if k in _os.environ}
if not _OMP_USER:
    _os.environ["GOMP_SPINCOUNT"] = DEFAULT_GOMP_SPINCOUNT

from kinema import _core  # noqa: E402
from kinema._info import SolveInfo
from kinema.errors import (
    ConvergenceError,
    DivergenceError,
    KinemaError,
    NotPositiveDefiniteError,
    StabilityError,
)
from kinema import diffusion, fem, fmm, grid, massspring, poisson, render, sparse, sph, vortex
from kinema import mesh, mpm, nbody
from kinema import contact
from kinema.scenes import Scene, SceneError
from kinema import io
from kinema import diff
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
    "nbody",
    "grid",
    "massspring",
    "fem",
    "mesh",
    "sph",
    "mpm",
    "contact",
    "diff",
    "torch",
    "render",
    "Scene",
    "SceneError",
    "io",
    "surface",
    "viewer",
    "show",
]


def __getattr__(name):
    # km.torch imports PyTorch (an optional extra, slow to import): only on first use.
    if name == "torch":
        import importlib
        return importlib.import_module("kinema.torch")
    raise AttributeError(f"module 'kinema' has no attribute {name!r}")


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
    info["openmp_wait"] = (", ".join(f"{k}={v}" for k, v in _OMP_USER.items()) + " (set by the user)" if _OMP_USER
                           else f"GOMP_SPINCOUNT={DEFAULT_GOMP_SPINCOUNT} (kinema default)")
    return info
