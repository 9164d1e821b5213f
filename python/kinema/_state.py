"""Assignment to state attributes: ``sim.x = array`` copies into the solver's own memory.

Every state array of a simulation class (``x``, ``v``, ``u``, ``density``, ``solid``, ...) is a
writable view; assigning to the attribute writes through that view (in place, so views handed
out earlier stay valid) after checking the shape and, for real arrays, that all values are finite.
"""

from __future__ import annotations

import numpy as np

from kinema._checks import as_float_array


def assign(view: np.ndarray, value, name: str) -> None:
    """Copies ``value`` into ``view`` (in place) or raises ValueError naming ``name``."""
    if view.dtype == np.bool_:
        a = np.asarray(value)
        if a.dtype != np.bool_ and not (a.dtype.kind in "iuf" and np.isin(a, (0, 1)).all()):
            raise ValueError(f"{name}: expected a bool array, got dtype {a.dtype}")
    else:
        a = as_float_array(value, name)
        if np.ndim(value) == 0:
            a = a.reshape(())
    if a.shape != view.shape and a.ndim != 0:
        raise ValueError(f"{name}: expected an array of shape {view.shape}, got shape {a.shape}")
    view[...] = a.astype(view.dtype, copy=False)


def state_property(getter, name: str, doc: str = None) -> property:
    """A property whose getter returns a view and whose setter copies into it."""

    def setter(self, value):
        assign(getter(self), value, name)

    return property(getter, setter, doc=doc or getter.__doc__)
