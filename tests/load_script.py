"""Imports a program of examples/ or bench/ from its path, as tests of those programs need
(they are scripts, not modules of the package)."""

import importlib.util
from pathlib import Path


def load_script(path: Path):
    spec = importlib.util.spec_from_file_location(Path(path).stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
