"""Scenes: a TOML file names a solver, its objects and the outputs; ``Scene.load(path).run(out)``
or ``kinema run path`` turns it into frames, a video, data files and a checkpoint.

Solvers are plugged in by one adapter module each (kinema/scenes/adapters/, registered in
``adapters.ADAPTERS``); example scenes live in kinema/scenes/examples/ (``kinema list``).
"""

from kinema.scenes.runner import RunResult
from kinema.scenes.scene import Scene, examples, resolve
from kinema.scenes.schema import SceneError

__all__ = ["Scene", "SceneError", "RunResult", "examples", "resolve"]
