"""Per-item status codes shared by the estimators.

Every batched estimator returns, next to its values, an integer ``status`` per item:
0 means the estimate is reliable; a non-zero code names the reason it is not. Values of an
item with a non-zero status are still finite (a documented fallback, e.g. a lower jet order
or zero curvature) unless stated otherwise, so that downstream code never meets a silent NaN.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["Status", "describe"]


class Status(IntEnum):
    """Reasons an estimate is unreliable (0 = OK)."""

    OK = 0
    #: The query point itself has NaN/inf coordinates; its outputs are NaN by definition
    #: (the only place a NaN is returned, and it is flagged).
    NONFINITE_INPUT = 1
    #: Fewer valid (finite, distinct) neighbours than coefficients of the requested order.
    TOO_FEW_POINTS = 2
    #: The neighbourhood is degenerate for the requested order (collinear points, a single
    #: scan line or ring): the fit fell back to a lower order.
    ORDER_REDUCED = 3
    #: Even the lowest order could not be fitted (all neighbours coincide or are collinear):
    #: the normal is not defined by the data.
    DEGENERATE = 4
    #: The least-squares system is ill-conditioned after preconditioning.
    ILL_CONDITIONED = 5
    #: The neighbourhood is not a height graph over the fitted frame (folds back).
    NOT_A_GRAPH = 6
    #: The neighbourhood reaches an edge shared by more than two faces (a non-manifold mesh,
    #: e.g. a fin hung on a surface): points of separate sheets were fitted as one surface.
    NON_MANIFOLD = 7


def describe(code: int) -> str:
    """Return a one-line human-readable description of a status code."""
    try:
        s = Status(int(code))
    except ValueError:
        return f"unknown status {code}"
    return s.name.lower().replace("_", " ")
