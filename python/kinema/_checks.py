"""Argument checking shared by the Python modules: clear ValueErrors naming the argument."""

from __future__ import annotations

import math

import numpy as np

# Largest grid (in cells) accepted without complaint: 2^31 cells of float64 is 16 GiB per field.
MAX_CELLS = 2**31


def as_float_array(x, name, *, ndim=None, finite=True):
    """``x`` as a C-contiguous float64 array, checked for dimension and finiteness.
    Complex input is refused (its imaginary part would be lost), as are values beyond float64."""
    kind = getattr(getattr(x, "dtype", None), "kind", None)
    if kind is None and not isinstance(x, (int, float, np.number)):
        try:
            kind = np.asarray(x).dtype.kind
        except (TypeError, ValueError, OverflowError):
            kind = None
    if kind == "c" or isinstance(x, complex):
        raise ValueError(f"{name}: expected real numbers, got complex values")
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name}: expected an array of real numbers ({exc})") from None
    if ndim is not None and a.ndim not in np.atleast_1d(ndim):
        want = " or ".join(str(d) for d in np.atleast_1d(ndim))
        raise ValueError(f"{name}: expected a {want}-dimensional array, got shape {a.shape}")
    if finite and not np.isfinite(a).all():
        bad = int(np.count_nonzero(~np.isfinite(a)))
        raise ValueError(f"{name}: contains {bad} non-finite value(s) (NaN or Inf)")
    return a


def positive(x, name):
    """``x`` as a float, which must be finite and > 0."""
    try:
        v = real(x, name)
    except ValueError:
        raise ValueError(f"{name}: expected a positive number, got {x!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {v}")
    return v


# Grid and particle spacings: a solver divides by h^2 and multiplies by h^3 (cell volumes,
# particle masses); outside this range one of them overflows or underflows.
SPACING_RANGE = (1e-100, 1e100)


def spacing(x, name):
    """``x`` as a positive float within SPACING_RANGE."""
    v = positive(x, name)
    lo, hi = SPACING_RANGE
    if not lo <= v <= hi:
        raise ValueError(f"{name}: {v} is outside [{lo:g}, {hi:g}]: the solver's 1/{name}^2 or "
                         f"{name}^3 would not be representable; choose other units")
    return v


# Schemes divide by dt and dt^2 (pressure solves, implicit matrices M / dt^2): below this a
# time step makes them overflow.
MIN_TIME_STEP = 1e-150


def time_step(x, name="dt"):
    """``x`` as a finite float >= MIN_TIME_STEP."""
    v = positive(x, name)
    if v < MIN_TIME_STEP:
        raise ValueError(f"{name}: {v} is below {MIN_TIME_STEP:g}: 1/{name}^2 would overflow float64; "
                         "choose other units")
    return v


def non_negative(x, name):
    """``x`` as a float, which must be finite and >= 0."""
    try:
        v = real(x, name)
    except ValueError:
        raise ValueError(f"{name}: expected a number >= 0, got {x!r}") from None
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {v}")
    return v


def real(x, name):
    """``x`` as a Python float: a real number (not bool, not complex) within float64's range.
    Not checked for finiteness (see :func:`finite`)."""
    if isinstance(x, (bool, np.bool_, complex, np.complexfloating, str, bytes)):
        raise ValueError(f"{name}: expected a real number, got {x!r}")
    if isinstance(x, np.ndarray) and x.ndim == 0:
        x = x[()]
    try:
        return float(x)
    except OverflowError:
        raise ValueError(f"{name}: {x!r} is beyond the range of a float64") from None
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a real number, got {x!r}") from None


def finite(x, name):
    """``x`` as a finite float."""
    v = real(x, name)
    if not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {v}")
    return v


def choice(value, name, options):
    """``value``, which must be one of ``options``."""
    if value not in options:
        raise ValueError(f"{name}: expected one of {sorted(options)}, got {value!r}")
    return value


# Counts and iteration limits cross into C++ as int64; counts of loops the user waits for are
# further limited by the callers (e.g. MAX_STEPS).
INDEX_MAX = 2**63 - 1
INT_MAX = 2**31 - 1


def integer(x, name, *, low=None, high=INDEX_MAX, allow_none=False):
    """``x`` as a Python int in [low, high] (None passes through when allowed). Floats, bools
    and strings are refused, so that 2.5 never silently becomes 2."""
    if x is None and allow_none:
        return None
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer, got {x!r}")
    v = int(x)
    if low is not None and v < low:
        raise ValueError(f"{name}: expected an integer >= {low}, got {v}")
    if high is not None and v > high:
        raise ValueError(f"{name}: expected an integer <= {high}, got {v}")
    return v


def positive_int(x, name, *, allow_none=False, high=INDEX_MAX):
    """``x`` as an int in [1, high] (or None when allowed)."""
    if x is None and allow_none:
        return None
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)) or x < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {x!r}")
    return integer(x, name, low=1, high=high)


def representable(value, names, what="the result"):
    """``value`` (computed from the arguments ``names``) when finite; otherwise a ValueError
    naming them: finite input whose result overflows float64 is a bad argument."""
    if np.isfinite(value).all():
        return value
    raise ValueError(f"{names}: {what} overflows float64 for these values (scale the input "
                     "into a smaller range)")


def finite_result(value, what):
    """``value`` (a float or array computed from a state) when finite; otherwise raises
    km.DivergenceError, as a step does on the same state."""
    if np.isfinite(value).all():
        return value
    from kinema.errors import DivergenceError
    raise DivergenceError(f"{what}: non-finite result; the state holds a NaN or Inf "
                          "(written into a state view, or left by a diverged run)")


def checked_state(state, keys, shape):
    """The arrays ``keys`` (each of ``shape``), time and steps of a particle system's
    ``state()`` dict, checked (ValueError naming the entry) before anything is restored."""
    if not isinstance(state, dict):
        raise ValueError(f"state: expected a dict from state(), got {type(state).__name__}")
    for key in (*keys, "time", "steps"):
        if key not in state:
            raise ValueError(f"state: missing {key!r}")
    arrays = []
    for key in keys:
        a = as_float_array(state[key], f"state[{key!r}]")
        if a.shape != shape:
            raise ValueError(f"state[{key!r}]: expected shape {shape}, got {a.shape}")
        arrays.append(a)
    time = finite(state["time"], "state['time']")
    steps = state["steps"]
    if isinstance(steps, np.ndarray) and steps.ndim == 0:
        steps = steps[()]
    return (*arrays, time, integer(steps, "state['steps']", low=0))


def grid_array(a, name):
    """``a`` as a float64 field on a 2D or 3D grid (every dimension >= 1, within MAX_CELLS)."""
    a = as_float_array(a, name, ndim=(2, 3))
    grid_shape(a.shape, name)
    return a


def grid_shape(shape, name):
    """A 2D or 3D grid shape of positive ints, within MAX_CELLS."""
    try:
        s = tuple(integer(n, name) for n in shape)
    except TypeError:
        raise ValueError(f"{name}: expected a tuple (nx, ny[, nz]), got {shape!r}") from None
    if len(s) not in (2, 3):
        raise ValueError(f"{name}: expected a 2D or 3D grid shape, got {s}")
    if min(s) < 1:
        raise ValueError(f"{name}: every grid dimension must be >= 1, got {s}")
    if math.prod(s) > MAX_CELLS:
        raise ValueError(f"{name}: {s} has {math.prod(s)} cells, more than the {MAX_CELLS} supported")
    return s


# ---------------------------------------------------------------------------- simulation objects
def simulation_object(cls):
    """Class decorator for the classes that own C++ state (km.grid.Fluid, km.sph.Fluid, ...).

    Thread safety: every method and property of one object runs under that object's re-entrant
    lock, so calls from several threads are serialised (a thread waiting for the lock releases
    the GIL and answers Ctrl-C). The C++ core releases the GIL in long calls; without the lock,
    two threads could step one object at once. Distinct objects do not share a lock and run in
    parallel. Arrays already handed out (the zero-copy state views) are not covered: writing
    into one while another thread steps is a data race on numbers (the C++ core clamps every
    position it turns into an index, so it cannot crash), not a supported way to share state.

    Copying: ``copy.copy``, ``copy.deepcopy`` and pickling raise a TypeError that says so; a
    shallow copy would share the C++ state (stepping one would advance both).
    """
    import functools
    import threading

    def lock_of(self):
        lock = self.__dict__.get("_kinema_lock")
        if lock is None:  # __init__ creates it; objects built without __init__ get one here
            lock = self.__dict__.setdefault("_kinema_lock", threading.RLock())
        return lock

    def locked(fn):
        @functools.wraps(fn)
        def wrapper(self, *args, **kwargs):
            with lock_of(self):
                return fn(self, *args, **kwargs)
        return wrapper

    for key, value in list(vars(cls).items()):
        if isinstance(value, property):
            setattr(cls, key, property(value.fget and locked(value.fget), value.fset and locked(value.fset),
                                       value.fdel and locked(value.fdel), value.__doc__))
        elif callable(value) and not isinstance(value, (staticmethod, classmethod, type)) and (
                key == "__init__" or not key.startswith("__")):
            setattr(cls, key, locked(value))

    name = f"km.{cls.__module__.removeprefix('kinema.')}.{cls.__qualname__}"

    def refuse_copy(self, *args):
        raise TypeError(f"{name} cannot be copied or pickled: it owns C++ solver state that a copy "
                        "would share; build a new object from the state arrays (copy those with "
                        "numpy), or save a checkpoint with km.Scene")

    cls.__copy__ = refuse_copy
    cls.__deepcopy__ = refuse_copy
    cls.__reduce_ex__ = refuse_copy
    return cls


# ---------------------------------------------------------------------------- meshes and vertices
def indices(value, name, n, shape_tail=None):
    """``value`` as a C-contiguous int64 array of vertex indices in [0, n), of shape
    (m, *shape_tail) when ``shape_tail`` is given (ValueError naming ``name`` otherwise)."""
    a = np.asarray(value)
    if a.size == 0:
        # an empty list ([] is float64 to numpy) holds no index of the wrong type
        a = a.reshape((0,) + (shape_tail or ())).astype(np.int64)
    if a.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected integer indices, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.int64)
    if shape_tail is not None and (a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail):
        raise ValueError(f"{name}: expected shape (m, {', '.join(map(str, shape_tail))}), "
                         f"got {a.shape}")
    if a.size and (a.min() < 0 or a.max() >= n):
        bad = int(a.ravel()[np.flatnonzero((a.ravel() < 0) | (a.ravel() >= n))[0]])
        raise ValueError(f"{name}: index {bad} outside [0, {n})")
    return a


def gravity_vector(gravity, d):
    """``gravity`` (None: no gravity) as a list of d floats [m/s^2]."""
    if gravity is None:
        return []
    g = as_float_array(gravity, "gravity", ndim=1)
    if g.shape != (d,):
        raise ValueError(f"gravity: expected {d} components, got shape {g.shape}")
    return [float(c) for c in g]


def user_stacklevel() -> int:
    """The ``stacklevel`` for warnings.warn, called from kinema, that names the first caller
    outside the kinema package (the user's line, whatever kinema frames lie between)."""
    import os
    import sys

    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(package):
        frame, level = frame.f_back, level + 1
    return level
