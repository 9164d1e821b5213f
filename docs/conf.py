"""Sphinx configuration of kinema's documentation (``bash scripts/docs.sh`` builds it into
build/docs/html with warnings as errors; scripts/test.sh runs it).

The API reference (api.md) is generated from the docstrings of the installed package: one
section per module of ``API_MODULES``, in that order, followed by any other public module of
the package (found automatically). Adding a module to the reference is therefore nothing, or
one line in API_MODULES to choose its place.
"""

import importlib
import pkgutil
import re

import kinema

project = "kinema"
author = "the kinema authors"
release = version = kinema.__version__
extensions = ["myst_parser", "sphinx.ext.autodoc"]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build"]
html_theme = "alabaster"
html_static_path = []
myst_heading_anchors = 3
autodoc_member_order = "bysource"
autodoc_default_options = {"show-inheritance": False}
nitpicky = False

#: the API reference, in this order; public modules not listed are appended after them
API_MODULES = [
    "kinema",
    "kinema.poisson",
    "kinema.diffusion",
    "kinema.sparse",
    "kinema.grid",
    "kinema.sph",
    "kinema.massspring",
    "kinema.fem",
    "kinema.fmm",
    "kinema.vortex",
    "kinema.nbody",
    "kinema.mpm",
    "kinema.diff",
    "kinema.torch",
    "kinema.mesh",
    "kinema.render",
    "kinema.io",
    "kinema.scenes",
    "kinema.scenes.scene",
    "kinema.scenes.runner",
    "kinema.errors",
]
#: modules that are programs or internals, not API
NOT_API = {"kinema.cli"}


def api_modules():
    found = [f"kinema.{m.name}" for m in pkgutil.iter_modules(kinema.__path__) if not m.name.startswith("_")]
    return API_MODULES + sorted(m for m in found if m not in API_MODULES and m not in NOT_API)


def _members(module, documented, seen):
    """The public names of ``module`` to describe there: its ``__all__`` (or, without one, the
    names it defines), leaving out objects described in an earlier section (``seen``) and
    objects whose own module has a section of its own."""
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n, v in vars(module).items()
                 if not n.startswith("_") and getattr(v, "__module__", None) == module.__name__]
    out = []
    for n in names:
        obj = getattr(module, n, None)
        home = getattr(obj, "__module__", module.__name__)
        if obj is None or type(obj).__name__ == "module" or id(obj) in seen:
            continue
        if home != module.__name__ and home in documented:
            continue
        if callable(obj) or isinstance(obj, type):
            seen.add(id(obj))
            out.append(n)
    return out


def _api_page(app, docname, source):
    if docname != "api":
        return
    parts = [source[0]]
    names = api_modules()
    seen = set()
    for name in names:
        module = importlib.import_module(name)
        members = _members(module, set(names), seen)
        option = f"   :members: {', '.join(members)}\n" if members else ""
        parts.append(f"\n## `{name}`\n\n```{{eval-rst}}\n.. automodule:: {name}\n{option}```\n")
    source[0] = "".join(parts)


# Docstrings are written as reStructuredText; one that does not parse cleanly (as a few
# pybind11 signatures do not) is shown verbatim rather than failing the warnings-as-errors build.
_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:(`[^`]+`)")


def _clean_rst(lines):
    import io

    import docutils.core
    import docutils.utils

    text = _ROLE.sub(r"`\1`", "\n".join(lines))
    stream = io.StringIO()
    try:
        docutils.core.publish_doctree(text, settings_overrides={
            "warning_stream": stream, "report_level": 2, "halt_level": 5, "file_insertion_enabled": False,
            "raw_enabled": False})
    except Exception:  # noqa: BLE001 -- any parser failure means: show it verbatim
        return False
    return not stream.getvalue()


def _docstring(app, what, name, obj, options, lines):
    if lines and not _clean_rst(lines):
        lines[:] = ["::", ""] + ["    " + line for line in lines] + [""]


def setup(app):
    app.connect("source-read", _api_page)
    app.connect("autodoc-process-docstring", _docstring)
