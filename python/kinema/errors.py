"""kinema's exception hierarchy.

Every package error derives from :class:`KinemaError`, itself a ``RuntimeError``. Errors that
are also about a bad argument (an unstable explicit step, a matrix that is not positive
definite) derive from ``ValueError`` too, so either ``except`` catches them.
"""

__all__ = [
    "KinemaError",
    "DivergenceError",
    "ConvergenceError",
    "StabilityError",
    "NotPositiveDefiniteError",
]


class KinemaError(RuntimeError):
    """Base class of kinema's errors."""


class DivergenceError(KinemaError):
    """A non-finite value or a blow-up was detected (message: quantity, step, hint)."""


class ConvergenceError(KinemaError):
    """An iterative solve hit ``max_iter`` without reaching ``tol``.

    ``info`` holds the :class:`kinema.SolveInfo` of the failed solve when available.
    """

    info = None


class StabilityError(KinemaError, ValueError):
    """An explicit scheme was asked for a step beyond its stability limit (with ``check=True``)."""


class NotPositiveDefiniteError(KinemaError, ValueError):
    """A Cholesky factorisation failed; ``column`` is the zero-based failing column."""

    column = None
