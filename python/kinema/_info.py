"""Small result records returned by solvers."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["SolveInfo"]


@dataclass(frozen=True)
class SolveInfo:
    """Statistics of an iterative solve.

    iterations: iterations performed.
    residual: relative 2-norm ||b - A x|| / ||b|| of the returned solution.
    converged: whether ``residual`` reached the requested tolerance.
    history: relative residual before the first and after each iteration.
    seconds: wall time of the solve [s].
    """

    iterations: int
    residual: float
    converged: bool
    history: list = field(default_factory=list, repr=False)
    seconds: float = 0.0
