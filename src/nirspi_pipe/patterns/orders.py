"""Scan orders: permutations of the ``n²`` Hadamard pattern indices.

An order is a permutation of the flat indices ``k = i·n + j`` (natural Sylvester rows ``i`` and
``j``, see :mod:`nirspi_pipe.patterns.hadamard`). ``ratio`` keeps the first ``round(ratio·n²)``
of them (at least one). Orders are computed in ``O(N log N)`` or better; none builds an
``N × N`` matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nirspi_pipe.errors import ConfigError

__all__ = ["ScanOrderBase", "Basic", "n_selected"]


def n_selected(ratio: float, n_patterns: int) -> int:
    """Number of patterns measured at sampling ``ratio`` out of ``n_patterns`` (at least 1)."""
    return max(1, min(n_patterns, int(round(float(ratio) * n_patterns))))


@dataclass(frozen=True)
class ScanOrderBase:
    """Common part of all scan orders: the sampling ratio and truncation.

    Attributes:
        ratio: fraction of the ``n²`` patterns measured, in (0, 1].
    """

    ratio: float = 1.0

    #: Whether ``order(n)[0]`` is always the DC (all-ones) pattern, index 0.
    dc_first = True

    def __post_init__(self) -> None:
        if not 0.0 < float(self.ratio) <= 1.0:
            raise ConfigError("ratio", self.ratio, "a fraction in (0, 1]")

    def order(self, n: int) -> np.ndarray:
        """The full permutation of ``n²`` flat pattern indices (int64)."""
        raise NotImplementedError

    def select(self, n: int) -> np.ndarray:
        """The first ``round(ratio · n²)`` indices of :meth:`order` (at least one)."""
        full = self.order(n)
        return full[: n_selected(self.ratio, full.size)]


@dataclass(frozen=True)
class Basic(ScanOrderBase):
    """The paper's *Basic* order (Fig. 2a): natural Sylvester order, ``k = 0, 1, …, n² − 1``."""

    def order(self, n: int) -> np.ndarray:
        return np.arange(n * n, dtype=np.int64)
