"""The grid problem that the fast-sweeping solvers share (:mod:`.sweeping`, :mod:`.second_order`,
:mod:`.opencl`): the problem, the result, and the anti-diagonal sweep orders. Kept apart from the
solvers so that they import it, and not each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["BIG", "SweepProblem", "SweepResult", "sweep_orders"]

#: Initial value of unknown cells: finite, so nothing ever becomes inf or NaN.
BIG = 1.0e12


@dataclass(frozen=True)
class SweepProblem:
    """One static HJ problem on an ``(r, c)`` pixel grid.

    Attributes:
        rhs: ``(r, c)`` right-hand side: ``F`` (model 0), ``W`` (model 1) or ``K`` (model 2);
            finite and > 0.
        fixed: ``(r, c)`` bool, Dirichlet cells (held at ``init``).
        init: ``(r, c)`` initial values; the Dirichlet data on ``fixed`` cells, a supersolution
            (large value) elsewhere. Pixel units.
        model: 0 eikonal, 1 perspective, 2 perspective with fall-off (see module docstring).
        xhat: ``(c,)`` normalised column coordinate ``x/f`` of pixel centres (models 1, 2).
        yhat: ``(r,)`` normalised row coordinate ``y/f`` of pixel centres (models 1, 2).
        focal_px: focal length in pixels (model 2).
    """

    rhs: np.ndarray
    fixed: np.ndarray
    init: np.ndarray
    model: int = 0
    xhat: np.ndarray | None = None
    yhat: np.ndarray | None = None
    focal_px: float = 1.0

    def sigmas(self) -> tuple[float, float]:
        """LF artificial viscosities ``(σx, σy)`` ≥ ``max|∂H/∂p|, max|∂H/∂q|`` (KOQ Eq. 2.5).

        Eikonal: ``|∂|∇z|/∂p| ≤ 1``. Perspective: with ``V = (p, q, x̂p + ŷq + 1)``,
        ``∂|V|/∂p = (p + x̂ V₃)/|V| ≤ sqrt(1 + x̂²)`` by Cauchy–Schwarz.
        """
        if self.model == 0:
            return 1.0, 1.0
        assert self.xhat is not None and self.yhat is not None
        return (
            float(np.sqrt(1.0 + np.max(self.xhat**2))),
            float(np.sqrt(1.0 + np.max(self.yhat**2))),
        )


@dataclass(frozen=True)
class SweepResult:
    """Solution and bookkeeping: ``z`` ``(r, c)`` (pixel units), single-direction ``sweeps``
    done, ``final_change`` = max |Δz| over the last round of four sweeps, ``converged``."""

    z: np.ndarray
    sweeps: int
    final_change: float
    converged: bool


@lru_cache(maxsize=16)
def sweep_orders(rows: int, cols: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Cells of an ``(rows, cols)`` grid grouped by anti-diagonal for the four KOQ orderings.

    Returns four ``(flat, starts)`` pairs in sweep order ``(i↑,j↑), (i↓,j↑), (i↓,j↓), (i↑,j↓)``:
    ``flat`` are row-major flat indices sorted by diagonal, ``starts`` the offsets where each
    diagonal begins (length ``n_diagonals + 1``).
    """
    i, j = np.divmod(np.arange(rows * cols), cols)
    out = []
    for key in (i + j, -(i - j), -(i + j), i - j):
        order = np.argsort(key, kind="stable")
        k = key[order]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1], True])
        out.append((order.astype(np.int64), starts))
    return tuple(out)
