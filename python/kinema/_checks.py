"""Argument checking shared by the Python modules: clear ValueErrors naming the argument."""

from __future__ import annotations

import math

import numpy as np

# Largest grid (in cells) accepted without complaint: 2^31 cells of float64 is 16 GiB per field.
MAX_CELLS = 2**31


def as_float_array(x, name, *, ndim=None, finite=True):
    """``x`` as a C-contiguous float64 array, checked for dimension and finiteness."""
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
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
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a positive number, got {x!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {v}")
    return v


def non_negative(x, name):
    """``x`` as a float, which must be finite and >= 0."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number >= 0, got {x!r}") from None
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {v}")
    return v


def choice(value, name, options):
    """``value``, which must be one of ``options``."""
    if value not in options:
        raise ValueError(f"{name}: expected one of {sorted(options)}, got {value!r}")
    return value


def positive_int(x, name, *, allow_none=False):
    """``x`` as an int >= 1 (or None when allowed)."""
    if x is None and allow_none:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {x!r}")
    return int(x)


def grid_shape(shape, name):
    """A 2D or 3D grid shape of positive ints, within MAX_CELLS."""
    try:
        s = tuple(int(n) for n in shape)
    except TypeError:
        raise ValueError(f"{name}: expected a tuple (nx, ny[, nz]), got {shape!r}") from None
    if len(s) not in (2, 3):
        raise ValueError(f"{name}: expected a 2D or 3D grid shape, got {s}")
    if min(s) < 1:
        raise ValueError(f"{name}: every grid dimension must be >= 1, got {s}")
    if math.prod(s) > MAX_CELLS:
        raise ValueError(f"{name}: {s} has {math.prod(s)} cells, more than the {MAX_CELLS} supported")
    return s
