"""Synthetic split-Hadamard acquisitions for testing solvers (ours and plugins') without a simulator.

A split pattern pair measures ``y± = Σ P± x`` with ``P± = (1 ± H)/2``, so ``y⁺ − y⁻`` is the
Hadamard coefficient and ``y⁺ + y⁻`` the total (docs/reconstruction.md). With a photon gain α the
readings are Poisson counts ``y± ~ Poisson(α P± x)``: the noise model the issue-15 case uses.
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.types import Acquisition

__all__ = ["split_hadamard"]


def split_hadamard(x: np.ndarray, alpha: float | None = None, seed: int = 0) -> Acquisition:
    """Every split Hadamard pattern of the ``n × n`` image ``x`` (relative radiance, ≥ 0).

    Args:
        x: the scene, square with a power-of-two side.
        alpha: photons per unit of relative radiance per pixel (Poisson counts, ``gain = α``);
            None gives the exact readings.
        seed: seed of the Poisson draws.
    """
    n = int(x.shape[0])
    c, total = fwht2(np.asarray(x, dtype=np.float64)).ravel(), float(np.sum(x))
    pos, neg = (total + c) / 2.0, (total - c) / 2.0
    idx = np.arange(n * n)
    if alpha is None:
        return Acquisition(n=n, indices=idx, y_pos=pos, y_neg=neg)
    rng = np.random.default_rng(seed)
    return Acquisition(
        n=n,
        indices=idx,
        y_pos=rng.poisson(alpha * pos).astype(float),
        y_neg=rng.poisson(alpha * neg).astype(float),
        gain=float(alpha),
    )
