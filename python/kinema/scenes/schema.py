"""A small schema layer for scene files: typed specs that validate a parsed TOML document,
fill in defaults and report the first mistake as ``file: key.path: expected ..., got ...``.

    SPEC = Table({"duration": Field(Real(gt=0)), "fps": Field(Real(gt=0), default=30.0)})
    config = SPEC.validate(raw, Context("scene.toml"))

Specs: :class:`Real`, :class:`Int`, :class:`Bool`, :class:`Str` (optionally one of a set),
:class:`Vec` (a list of numbers of a fixed or spatial length), :class:`ListOf`, :class:`Table`
(closed: unknown keys are errors) and :class:`Tagged` (a table whose ``type``-like key selects
one of several tables). Vectors declared ``spatial`` are recorded in the context so that the
scene can check them all against its dimension once the solver has fixed it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

REQUIRED = object()


class SceneError(ValueError):
    """A scene file that cannot be used: names the file, the key path and what was expected."""

    def __init__(self, file, path, message):
        self.file, self.path = str(file), path
        where = f"{self.file}: {path}" if path else self.file
        super().__init__(f"{where}: {message}")


@dataclass
class Context:
    """Where validation is (the file, for messages) and what it has seen (spatial vectors)."""

    file: str
    spatial: list = field(default_factory=list)  # (path, length) of every spatial vector

    def error(self, path, message):
        return SceneError(self.file, path, message)


def _got(value):
    kind = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
            list: "an array", dict: "a table"}.get(type(value), type(value).__name__)
    text = repr(value)
    return f"{kind} {text if len(text) <= 40 else text[:37] + '...'}"


def _join(path, key):
    return f"{path}.{key}" if path else key


class Spec:
    """One expected kind of value; ``validate`` returns the (normalised) value or raises."""

    expected = "a value"

    def validate(self, value, ctx, path):
        raise NotImplementedError

    def fail(self, value, ctx, path, expected=None):
        return ctx.error(path, f"expected {expected or self.expected}, got {_got(value)}")


class Real(Spec):
    """A finite number (TOML integer or float), optionally bounded: gt/ge below, le above."""

    def __init__(self, *, gt=None, ge=None, le=None):
        self.gt, self.ge, self.le = gt, ge, le
        bounds = [f"{op} {v}" for op, v in ((">", gt), (">=", ge), ("<=", le)) if v is not None]
        self.expected = "a number" + (" " + " and ".join(bounds) if bounds else "")

    def validate(self, value, ctx, path):
        if isinstance(value, float) and not math.isfinite(value):  # TOML's nan and inf
            raise self.fail(value, ctx, path, self.expected.replace("a number", "a finite number", 1))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(value, ctx, path)
        if (self.gt is not None and not value > self.gt) or (self.ge is not None and not value >= self.ge) \
                or (self.le is not None and not value <= self.le):
            raise self.fail(value, ctx, path)
        return float(value)


class Int(Spec):
    """An integer, optionally bounded: ge below, le above."""

    def __init__(self, *, ge=None, le=None):
        self.ge, self.le = ge, le
        bounds = [f"{op} {v}" for op, v in ((">=", ge), ("<=", le)) if v is not None]
        self.expected = "an integer" + (" " + " and ".join(bounds) if bounds else "")

    def validate(self, value, ctx, path):
        if isinstance(value, bool) or not isinstance(value, int) or (self.ge is not None and value < self.ge) \
                or (self.le is not None and value > self.le):
            raise self.fail(value, ctx, path)
        return value


class Bool(Spec):
    expected = "true or false"

    def validate(self, value, ctx, path):
        if not isinstance(value, bool):
            raise self.fail(value, ctx, path)
        return value


class Str(Spec):
    def __init__(self, choices=None):
        self.choices = tuple(choices) if choices else None
        self.expected = "a string" if not self.choices else "one of " + ", ".join(f'"{c}"' for c in self.choices)

    def validate(self, value, ctx, path):
        if not isinstance(value, str) or (self.choices and value not in self.choices):
            raise self.fail(value, ctx, path)
        return value


class Vec(Spec):
    """An array of ``length`` items of ``item`` (default Real()); ``spatial=True``: the length
    must be the scene's dimension (2 or 3), checked by the scene after the solver is known."""

    def __init__(self, length=None, item=None, *, spatial=False):
        self.length, self.item, self.spatial = length, item or Real(), spatial
        n = "2 or 3" if spatial else str(length) if length else "any number of"
        self.expected = f"an array of {n} items, each {self.item.expected}"

    def validate(self, value, ctx, path):
        if not isinstance(value, list):
            raise self.fail(value, ctx, path)
        if (self.spatial and len(value) not in (2, 3)) or (self.length and len(value) != self.length):
            raise self.fail(value, ctx, path)
        out = [self.item.validate(v, ctx, f"{path}[{i}]") for i, v in enumerate(value)]
        if self.spatial:
            ctx.spatial.append((path, len(out)))
        return out


class ListOf(Spec):
    def __init__(self, item, *, min_length=0):
        self.item, self.min_length = item, min_length
        least = f"at least {min_length} " if min_length else ""
        self.expected = f"an array of {least}items, each {item.expected}"

    def validate(self, value, ctx, path):
        if not isinstance(value, list) or len(value) < self.min_length:
            raise self.fail(value, ctx, path)
        return [self.item.validate(v, ctx, f"{path}[{i}]") for i, v in enumerate(value)]


@dataclass
class Field:
    """A key of a table: its spec, its default (REQUIRED if none; None: optional) and what it means."""

    spec: Spec
    default: object = REQUIRED
    doc: str = ""


class Table(Spec):
    """A closed table: every key must be declared; missing keys take their defaults."""

    def __init__(self, fields, doc=""):
        self.fields, self.doc = dict(fields), doc
        self.expected = "a table"

    def validate(self, value, ctx, path):
        if not isinstance(value, dict):
            raise self.fail(value, ctx, path)
        for key in value:
            if key not in self.fields:
                known = ", ".join(sorted(self.fields)) or "none"
                raise ctx.error(_join(path, key), f"unknown key (known keys here: {known})")
        out = {}
        for key, f in self.fields.items():
            if key in value:
                out[key] = f.spec.validate(value[key], ctx, _join(path, key))
            elif f.default is REQUIRED:
                raise ctx.error(_join(path, key), f"missing required key ({f.spec.expected})")
            else:
                out[key] = f.default
        return out


class Tagged(Spec):
    """A table whose key ``tag`` names one of ``variants`` (each a Table without the tag)."""

    def __init__(self, tag, variants):
        self.tag, self.variants = tag, dict(variants)
        self.expected = f"a table with {tag} = " + " | ".join(f'"{v}"' for v in self.variants)

    def validate(self, value, ctx, path):
        if not isinstance(value, dict):
            raise self.fail(value, ctx, path)
        kind = value.get(self.tag)
        if kind is None:
            raise ctx.error(_join(path, self.tag), f"missing required key (one of {self.choices()})")
        if kind not in self.variants:
            raise ctx.error(_join(path, self.tag), f"expected one of {self.choices()}, got {_got(kind)}")
        rest = {k: v for k, v in value.items() if k != self.tag}
        out = self.variants[kind].validate(rest, ctx, path)
        out[self.tag] = kind
        return out

    def choices(self):
        return ", ".join(f'"{v}"' for v in self.variants)


# --------------------------------------------------------------------------- shared pieces

REGION = Tagged("shape", {
    "box": Table({"lower": Field(Vec(spatial=True), doc="lower corner [m]"),
                  "upper": Field(Vec(spatial=True), doc="upper corner [m]")}),
    "sphere": Table({"center": Field(Vec(spatial=True), doc="centre [m]"),
                     "radius": Field(Real(gt=0), doc="radius [m]")}),
})
"""A region of space: ``{shape = "box", lower = [..], upper = [..]}`` or
``{shape = "sphere", center = [..], radius = r}`` (a disc in 2D)."""


def describe(spec, indent="  "):
    """The keys of a table spec as indented text lines (for ``kinema list --keys``)."""
    lines = []
    if isinstance(spec, Tagged):
        for name, variant in spec.variants.items():
            lines.append(f'{indent}{spec.tag} = "{name}"')
            lines += describe(variant, indent + "  ")
        return lines
    for key, f in spec.fields.items():
        default = "required" if f.default is REQUIRED else f"default {f.default!r}"
        lines.append(f"{indent}{key}: {f.spec.expected} ({default}){' - ' + f.doc if f.doc else ''}")
    return lines
