"""One adapter module per solver, registered by name in ADAPTERS.

An adapter module defines:

* ``SOLVER``: the schema Table of its ``[solver]`` options (besides ``type``);
* ``OBJECTS``: object type name -> schema Table of that ``[[objects]]`` entry (besides ``type``);
* ``dimension(solver, objects) -> 2 or 3``: the scene's dimension, from validated options;
* ``Simulation(scene)``: a subclass of :class:`kinema.scenes.adapters.base.Simulation` that
  builds the solver and exactly the objects the scene names.

Adding a solver is one new module here and one line in ADAPTERS. Modules are imported only
when a scene names them, so a scene builds (and imports) nothing it does not use.
"""

from __future__ import annotations

import importlib

ADAPTERS = {
    "grid": "kinema.scenes.adapters.grid",
    "sph": "kinema.scenes.adapters.sph",
    "massspring": "kinema.scenes.adapters.massspring",
    "fem": "kinema.scenes.adapters.fem",
    "vortex": "kinema.scenes.adapters.vortex",
    "mpm": "kinema.scenes.adapters.mpm",
    "nbody": "kinema.scenes.adapters.nbody",
}


def load(name):
    """The adapter module of solver ``name`` (a key of ADAPTERS)."""
    return importlib.import_module(ADAPTERS[name])
