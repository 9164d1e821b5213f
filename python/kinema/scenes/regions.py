"""Regions of space named in scene files (schema.REGION): membership and bounding boxes."""

from __future__ import annotations

import numpy as np


def contains(region, points) -> np.ndarray:
    """(n,) bool: which of the (n, d) points lie in the region (closed box or ball)."""
    p = np.asarray(points, dtype=float)
    if region["shape"] == "box":
        return np.all((p >= region["lower"]) & (p <= region["upper"]), axis=1)
    return np.sum((p - region["center"]) ** 2, axis=1) <= region["radius"] ** 2


def bounds(region):
    """(lower, upper) of the region's bounding box, as float arrays."""
    if region["shape"] == "box":
        return np.array(region["lower"], float), np.array(region["upper"], float)
    c = np.array(region["center"], float)
    return c - region["radius"], c + region["radius"]
