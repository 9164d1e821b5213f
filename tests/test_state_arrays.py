"""Every state array of every simulation class is assignable alike: ``sim.x = array`` copies into
the solver's memory (views handed out earlier see the new values), after a shape check that
raises a ValueError naming the attribute. (km.grid.Fluid's arrays: tests/test_grid.py.)"""

import numpy as np
import pytest

import kinema as km


def sims():
    x, springs = km.massspring.cloth(4, 3, 1.0)
    yield "massspring", km.massspring.System(x, springs, stiffness=100.0), ("x", "v")
    v, tets = km.fem.box_mesh((0, 0, 0), (1, 1, 1), 1)
    yield "fem", km.fem.Body(v, tets, youngs_modulus=1e4, poisson_ratio=0.3, density=10.0), ("x", "v")
    p = km.sph.block((0, 0), (0.1, 0.1), 0.02)
    yield "sph", km.sph.Fluid(p, 0.02), ("x", "v", "density", "pressure")


@pytest.mark.parametrize("name, sim, attrs", list(sims()), ids=lambda v: v if isinstance(v, str) else "")
def test_state_arrays_are_assignable_in_place_with_a_shape_check(name, sim, attrs):
    for k, attr in enumerate(attrs):
        view = getattr(sim, attr)
        value = np.full(view.shape, 0.25 * (k + 1)) + np.arange(view.size).reshape(view.shape) * 1e-3
        setattr(sim, attr, value)
        np.testing.assert_array_equal(view, value)  # in place: the old view sees the new values
        np.testing.assert_array_equal(getattr(sim, attr), value)
        wrong = np.zeros((view.shape[0] + 1,) + view.shape[1:])
        with pytest.raises(ValueError, match=f"{attr}: expected an array of shape"):
            setattr(sim, attr, wrong)
        with pytest.raises(ValueError, match=attr):
            setattr(sim, attr, np.full(view.shape, np.nan))
