"""Exact fast inverse of a Hadamard acquisition (zero-filled when undersampled)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nirspi_pipe.patterns.hadamard import ifwht
from nirspi_pipe.solvers.common import checked_coefficients, require_hadamard
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["FWHTSolver", "zero_filled_inverse"]


def zero_filled_inverse(n: int, indices: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """Image from measured 2D Hadamard coefficients, unmeasured ones set to zero.

    ``O = H_N c / N`` with ``c`` the length-``n²`` coefficient vector (Eq. 2 normalised: the
    correlation of measurements with their patterns, divided by ``N``). Exact when every
    pattern was measured. Units: those of ``coefficients`` (per pixel). Cost ``O(N log N)``.
    """
    full = np.zeros(n * n, dtype=np.float64)
    full[np.asarray(indices, dtype=np.int64)] = coefficients
    return ifwht(full).reshape(n, n)


@dataclass(frozen=True)
class FWHTSolver:
    """Solver ``fwht``: the exact inverse by the fast Walsh–Hadamard transform.

    Requires a Hadamard acquisition (no explicit pattern matrix). With every pattern measured it
    reconstructs the (noisy) scene exactly; with fewer, the missing coefficients are zero.
    """

    def solve(self, acquisition: Acquisition) -> Image2D:
        require_hadamard(acquisition, "fwht")
        coeffs = checked_coefficients(acquisition, "fwht")
        image = zero_filled_inverse(acquisition.n, acquisition.indices, coeffs)
        return Image2D(image, info={"iterations": 1, "stop_reason": "direct"})
