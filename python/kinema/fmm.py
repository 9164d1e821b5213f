"""The 2D fast multipole method for the Laplace potential of point charges.

    phi(x) = sum_j q_j log|x - y_j|,    grad phi(x) = sum_j q_j (x - y_j) / |x - y_j|^2

:func:`laplace2d` evaluates both in O(N + M) work with the adaptive FMM of Greengard & Rokhlin
(1987) and Carrier, Greengard & Rokhlin (1988): complex-form multipole and local expansions
(phi = Re sum_j q_j log(z - z_j)) on an adaptive quadtree, so clustered or very non-uniform
points keep the cost linear. The expansion order follows from ``eps``, the requested relative
2-norm error ``||phi - phi_exact|| / ||phi_exact||`` (1e-3 ... 1e-13; the gradient meets it
too). :func:`direct2d` is the exact O(N M) sum with the same signature.

Pairs at distance zero are left out: the self term when ``targets`` is None, and coincident
(duplicate) points, whose log|0| would be infinite. Both functions run in parallel (OpenMP,
``km.set_num_threads``), release the GIL and stop on Ctrl-C.
"""

from __future__ import annotations

import numpy as np

from kinema import _core
from kinema._checks import as_float_array, positive_int, real, representable

__all__ = ["laplace2d", "direct2d", "laplace3d", "direct3d", "last_info"]

_last_info: dict = {}


_AXES = {2: "(x, y) pairs", 3: "(x, y, z) coordinates"}


def _points(x, name, dim):
    if np.iscomplexobj(x):
        raise ValueError(f"{name}: expected real {_AXES[dim]}, got complex numbers")
    a = as_float_array(x, name, ndim=2)
    if a.shape[1] != dim:
        raise ValueError(f"{name}: expected shape (n, {dim}), got {a.shape}")
    return a


def _inputs(sources, charges, targets, dim):
    """Checked float64 sources (N, dim), charges (N,) (a scalar is one charge for all) and
    targets (M, dim) or None; shared by the 2D and 3D functions."""
    src = _points(sources, "sources", dim)
    if np.iscomplexobj(charges):
        raise ValueError("charges: expected real charges, got complex numbers")
    q = as_float_array(charges, "charges", ndim=(0, 1))
    if np.ndim(charges) == 0:  # one charge for all (as_float_array returns it with shape (1,))
        q = np.full(src.shape[0], float(q[0]))
    if q.shape != (src.shape[0],):
        raise ValueError(f"charges: expected shape ({src.shape[0]},) (one per source), got {q.shape}")
    tgt = None if targets is None else _points(targets, "targets", dim)
    return src, q, tgt


def _eps(eps):
    v = real(eps, "eps")
    if not (1e-15 <= v < 1):
        raise ValueError(f"eps: expected a number in [1e-15, 1) (double precision cannot do "
                         f"better than ~1e-15), got {v}")
    return v


def _count(x, name):
    if x is None:
        return 0
    return positive_int(x, name)


def laplace2d(sources, charges, targets=None, *, eps=1e-10, gradient=False, order=None,
              leaf_size=None):
    """phi(x) = sum_j q_j log|x - y_j| (and its gradient) by the fast multipole method.

    sources: (N, 2) source positions [m]. charges: (N,) charges q_j (or a scalar for all).
    targets: (M, 2) evaluation points, or None for the sources themselves (self term left out).
    eps: relative 2-norm error to meet, 1e-15 <= eps < 1 (tested from 1e-3 to 1e-13).
    gradient: also return grad phi.
    order, leaf_size: override the expansion order p (1..100) and the leaf capacity, which
    are otherwise chosen from eps (for benchmarks and studies; eps is then not guaranteed).

    Returns phi (M,), or (phi, grad) with grad of shape (M, 2) when ``gradient``.
    Statistics of the last call (order, boxes, depth, seconds per pass) are in
    :func:`last_info`.
    """
    src, q, tgt = _inputs(sources, charges, targets, 2)
    e = _eps(eps)
    p = _count(order, "order")
    if p > 100:
        raise ValueError(f"order: expected an integer in 1..100, got {order}")
    phi, grad, info = _core.fmm.laplace2d(src, q, tgt, e, bool(gradient), p,
                                          _count(leaf_size, "leaf_size"))
    representable(phi, "sources, charges", "the potential")
    if gradient:
        representable(grad, "sources, charges", "the gradient")
    _last_info.clear()
    _last_info.update(info)
    return (phi, grad) if gradient else phi


def direct2d(sources, charges, targets=None, *, eps=None, gradient=False):
    """The exact O(N M) sum of :func:`laplace2d`, in parallel; same arguments (eps is ignored)."""
    src, q, tgt = _inputs(sources, charges, targets, 2)
    if eps is not None:
        _eps(eps)
    phi, grad = _core.fmm.direct2d(src, q, tgt, bool(gradient))
    representable(phi, "sources, charges", "the potential")
    if gradient:
        representable(grad, "sources, charges", "the gradient")
    return (phi, grad) if gradient else phi


def last_info() -> dict:
    """Statistics of the last :func:`laplace2d` call: order, leaf_size, boxes, depth, seconds_*."""
    return dict(_last_info)


# ---------------------------------------------------------------------------------------- 3D

_NEAR_KERNELS = {"laplace": 0, "plummer": 1, "gaussian": 2}

# Below this many source-target pairs the direct sum is as fast as the FMM (bench/fmm/fmm3d_bench.py
# measures the crossover); laplace3d then sums directly, which is exact.
_DIRECT_PAIRS_3D = 2_000_000


_M2L = {"auto": 0, "dense": 1, "rotation": 2}


def _eval3d(src, q, tgt, *, eps, derivatives, kernel="laplace", length=0.0, min_width=0.0,
            order=0, leaf_size=0, direct=False, m2l="auto"):
    """The 3D engine shared by laplace3d, km.nbody and km.vortex (checked inputs).

    q: (N, C) charge components. Returns (out (M, C, width), info); width 1 (phi), 4 (phi,
    grad) or 10 (phi, grad, hessian xx xy xz yy yz zz). The smooth kernels ("plummer",
    "gaussian") are finite at r = 0: only the self pair (tgt None) is left out, and a distinct
    source at a target's position adds q f(0); "laplace" leaves out every pair at distance 0.
    """
    q2 = np.ascontiguousarray(q[:, None] if q.ndim == 1 else q, dtype=np.float64)
    out, info = _core.fmm.eval3d(src, q2, tgt, float(eps), int(derivatives), _NEAR_KERNELS[kernel],
                                 float(length), float(min_width), int(order), int(leaf_size),
                                 bool(direct), _M2L[m2l])
    return out, info


def laplace3d(sources, charges, targets=None, *, eps=1e-10, gradient=False, order=None,
              leaf_size=None, m2l="auto"):
    """phi(x) = sum_j q_j / |x - y_j| (and its gradient) by the fast multipole method.

    sources: (N, 3) source positions [m]. charges: (N,) charges q_j (or a scalar for all).
    targets: (M, 3) evaluation points, or None for the sources themselves (the self term
    left out). A target and a charged source at exactly the same position (equal
    coordinates) are left out too, their 1/0 being infinite; ``last_info()["coincident"]``
    counts such pairs (in the self case those whose two charges are both nonzero). Distinct
    points are summed however close or far (a distance whose square underflows or overflows
    is not 0); a potential or gradient beyond the float range raises ValueError.
    eps: relative 2-norm error of phi to meet, 1e-15 <= eps < 1 (tested from 1e-3 to 1e-12;
    the gradient's relative error is of the same size).
    gradient: also return grad phi = -sum_j q_j (x - y_j) / |x - y_j|^3.
    order, leaf_size: override the expansion order p (1..40) and the leaf capacity, otherwise
    chosen from eps (for benchmarks and studies; eps is then not guaranteed). By default the
    root box of evenly spread points is enlarged by a measured factor in [1, 2) so that the
    leaves hold ~10 (p + 1) points (``last_info()["root_scale"]``); a given leaf_size keeps
    the points' bounding cube.
    m2l: how the multipole-to-local translations run: "dense" (precomputed (p+1)^2 square
    matrices applied as batched matrix products, O(p^4) each), "rotation" (rotate to the z
    axis, translate along it, rotate back: O(p^3) each) or "auto" (by the order; the two agree
    to rounding).

    Problems of fewer than about 2e6 source-target pairs are summed directly (exact, and
    faster there). Returns phi (M,), or (phi, grad) with grad of shape (M, 3). Statistics of
    the last call are in :func:`last_info`.
    """
    src, q, tgt = _inputs(sources, charges, targets, 3)
    e = _eps(eps)
    if m2l not in _M2L:
        raise ValueError(f"m2l: expected 'auto', 'dense' or 'rotation', got {m2l!r}")
    p = _count(order, "order")
    if p > 40:
        raise ValueError(f"order: expected an integer in 1..40, got {order}")
    m = src.shape[0] if tgt is None else tgt.shape[0]
    direct = order is None and leaf_size is None and src.shape[0] * m <= _DIRECT_PAIRS_3D
    out, info = _eval3d(src, q, tgt, eps=e, derivatives=1 if gradient else 0, order=p,
                        leaf_size=_count(leaf_size, "leaf_size"), direct=direct, m2l=m2l)
    info["direct"] = direct
    _last_info.clear()
    _last_info.update(info)
    representable(out, "sources, charges", "the potential or its gradient")
    phi = out[:, 0, 0].copy()
    return (phi, out[:, 0, 1:4].copy()) if gradient else phi


def direct3d(sources, charges, targets=None, *, eps=None, gradient=False):
    """The exact O(N M) sum of :func:`laplace3d`, in parallel; same arguments (eps is ignored)."""
    src, q, tgt = _inputs(sources, charges, targets, 3)
    if eps is not None:
        _eps(eps)
    out, _ = _eval3d(src, q, tgt, eps=1e-15, derivatives=1 if gradient else 0, direct=True)
    representable(out, "sources, charges", "the potential or its gradient")
    phi = out[:, 0, 0].copy()
    return (phi, out[:, 0, 1:4].copy()) if gradient else phi
