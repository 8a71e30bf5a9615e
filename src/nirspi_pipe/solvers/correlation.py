"""Solver ``correlation``: the paper's Eq. (2), the measurement-weighted sum of the patterns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.solvers.common import checked_coefficients
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["CorrelationSolver", "correlate_hadamard"]


def correlate_hadamard(n: int, indices: np.ndarray, coefficients: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """``Σ_k c_k P_k`` over the measured Hadamard patterns ``P_k = h_i h_jᵀ`` (``n × n``).

    Computed as written, pattern by pattern, but batched: ``H[I]ᵀ diag(c) H[J]`` over chunks of
    ``chunk`` measurements, so the cost is ``O(m · N)`` (``m`` measurements, ``N = n²``) and the
    memory ``O(chunk · n)``; no ``N × N`` matrix. Units: those of ``coefficients``.
    """
    h = sylvester(n)
    idx = np.asarray(indices, dtype=np.int64)
    out = np.zeros((n, n))
    for start in range(0, idx.size, chunk):
        sl = slice(start, start + chunk)
        rows = h[idx[sl] // n]  # (b, n): h_i of each pattern
        cols = h[idx[sl] % n]  # (b, n): h_j
        out += (rows * coefficients[sl, None]).T @ cols
    return out


@dataclass(frozen=True)
class CorrelationSolver:
    """Solver ``correlation``: ``O = α Σ_i S_i Φ_i`` (Eq. 2) with ``α = 1/N``.

    The paper's Eq. (2) leaves ``α`` as a detector factor; with calibrated measurements
    (``Acquisition.coefficients``) and ±1 Hadamard patterns, ``α = 1/N`` makes the full
    acquisition exact (``H H = N·I``), and undersampled it is the zero-filled inverse, only
    computed the slow way, ``O(m · N)``: it is the time reference for the fast solvers. With
    explicit patterns it is Eq. (2)'s ``G = Pᵀ y`` normalised: ``a·G + b`` with the gain ``a`` and
    offset ``b`` that best reproduce the measurements (least squares over the two numbers,
    ``min ‖P(a G + b) − y‖``). For a full set of ±1 patterns that is ``a = 1/N``, ``b = 0`` (exact);
    for 0/1 patterns ``PᵀP ≈ (m/4)(I + 11ᵀ)``, so ``G`` is the image plus a large constant, which
    ``b`` removes and ``a`` scales back to relative radiance (``info.alpha``, ``info.offset``).

    Attributes:
        chunk: measurements accumulated per batched product (memory ``chunk × n``).
    """

    chunk: int = 4096

    def __post_init__(self) -> None:
        if not isinstance(self.chunk, (int, np.integer)) or self.chunk < 1:
            raise ConfigError("chunk", self.chunk, "an integer >= 1")

    def solve(self, acquisition: Acquisition) -> Image2D:
        c = checked_coefficients(acquisition, "correlation")
        n, size = acquisition.n, acquisition.n_pixels
        if acquisition.patterns is None:
            image = correlate_hadamard(n, acquisition.indices, c, self.chunk) / size  # Eq. (2)
        else:
            p = np.asarray(acquisition.patterns, dtype=np.float64)
            g = p.T @ c  # Eq. (2), before its factor
            design = np.stack([p @ g, p.sum(axis=1)], axis=1)  # P g and P 1
            (alpha, offset), *_ = np.linalg.lstsq(design, c, rcond=None)
            image = (alpha * g + offset).reshape(n, n)
            return Image2D(
                image, info={"iterations": 1, "stop_reason": "direct", "alpha": float(alpha), "offset": float(offset)}
            )
        return Image2D(image, info={"iterations": 1, "stop_reason": "direct"})
