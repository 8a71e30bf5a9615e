"""Noise level of an acquisition, and a regularisation weight that follows it (SURE).

Noise estimate (:func:`estimate_noise`), in calibrated coefficient units (those of
``Acquisition.coefficients()``), per ±1 measurement, first rule that applies:

1. ``declared``: the source or recording states it, ``acquisition.derived["declared_noise_sigma"]``
   (detector units of one differential reading ``y⁺ − y⁻``; divided by the gain here).
2. ``pair_sums``: split acquisitions. Each pair's sum ``s_k = y⁺_k + y⁻_k`` is the total light on
   the scene for *every* pattern (the two halves tile the field), so it is constant without
   noise, and with independent noise in the two halves ``var(s_k) = var(y⁺) + var(y⁻) =
   var(y⁺ − y⁻)``: the spread of the sums *is* the noise of the measurements. We take the
   median absolute deviation of successive differences ``Δs`` (÷ √2, × 1.4826 for a Gaussian),
   which ignores slow drift of the light and a few outliers (Donoho & Johnstone 1994's MAD rule).
   Poisson noise of a split pair has the same variance for every pattern (``α Σx``), so one σ holds.
3. ``high_sequency``: differential-only data: MAD of the measured coefficients whose two
   sequencies are both in the upper half (mostly noise for natural scenes; overestimates on
   textured ones), when at least 16 are measured.
4. ``none``: nothing to estimate from; σ = 0 (the data are treated as exact).

Weight (:func:`sure_weight`): Stein's unbiased risk estimate of the error of the predicted
measurements ``ŷ(λ) = A x_λ(y)``, for ``y = Ax + w``, ``w ~ N(0, σ² I)``::

    SURE(λ) = ‖y − ŷ(λ)‖² − m σ² + 2 σ² div_y ŷ(λ)

with the divergence by one Monte-Carlo probe (Ramani, Blu & Unser, IEEE TIP 17(9), 2008):
``div ≈ bᵀ(ŷ(y + εb) − ŷ(y))/ε``, ``b ~ N(0, I)`` from a fixed seed, ``ε = 0.01 σ``. λ minimises
it over a bracket of ``[0.1, 10] σ_px`` (``σ_px = σ/√s``, the noise of one pixel of the
least-squares image, ``s`` the data term's normalisation) by scipy's bounded Brent search in
``log λ``. At full Hadamard sampling SURE is the image's mean squared error up to a constant, so the
chosen weight is the oracle one up to the search tolerance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from nirspi_pipe.patterns.orders import sequency_of_rows
from nirspi_pipe.types import Acquisition

__all__ = ["NoiseEstimate", "estimate_noise", "sure_weight", "SURE_BRACKET", "SURE_EPS"]

#: Search range of λ in units of the least-squares image's pixel noise σ_px. The SURE-optimal ROF
#: weight measured on the camera image (Poisson α = 10, 100, 1000) is 0.65–0.95 σ_px
#: (``tests/test_adaptive.py``); the range is that ×/÷ 10 or more.
SURE_BRACKET = (0.1, 10.0)
#: Monte-Carlo SURE step, in units of σ (Ramani et al. 2008 use a small fraction of σ).
SURE_EPS = 0.01
#: Normal-consistency factor of the median absolute deviation.
MAD_TO_SIGMA = 1.482602218505602


@dataclass(frozen=True)
class NoiseEstimate:
    """``sigma``: noise standard deviation of one calibrated ±1 measurement (relative radiance ×
    pixels); ``method``: which rule of the module doc gave it."""

    sigma: float
    method: str


def _mad(v: np.ndarray) -> float:
    return float(MAD_TO_SIGMA * np.median(np.abs(v - np.median(v))))


def estimate_noise(acquisition: Acquisition) -> NoiseEstimate:
    """The noise of ``acquisition.coefficients()`` by the first applicable rule (module doc)."""
    gain = float(acquisition.gain) if acquisition.gain else 1.0
    declared = acquisition.derived.get("declared_noise_sigma") if acquisition.derived else None
    if declared is not None and np.isfinite(declared) and declared >= 0:
        return NoiseEstimate(float(declared) / abs(gain), "declared")
    if acquisition.y_neg is not None and len(acquisition.y_pos) >= 3:
        s = (np.asarray(acquisition.y_pos, np.float64) + np.asarray(acquisition.y_neg, np.float64)) / abs(gain)
        s = s[np.isfinite(s)]
        if s.size >= 3:
            return NoiseEstimate(_mad(np.diff(s)) / np.sqrt(2.0), "pair_sums")
    if acquisition.patterns is None:
        n = acquisition.n
        idx = np.asarray(acquisition.indices, dtype=np.int64)
        seq = sequency_of_rows(n)
        high = (seq[idx // n] >= n // 2) & (seq[idx % n] >= n // 2)
        c = np.asarray(acquisition.coefficients(), np.float64)[high]
        c = c[np.isfinite(c)]
        if c.size >= 16:
            return NoiseEstimate(_mad(c), "high_sequency")
    return NoiseEstimate(0.0, "none")


def sure_weight(
    solve: Callable[[np.ndarray, float], np.ndarray],
    forward: Callable[[np.ndarray], np.ndarray],
    y: np.ndarray,
    sigma: float,
    sigma_px: float,
    seed: int = 0,
    xatol: float = 0.05,
) -> tuple[float, dict[str, float]]:
    """The weight λ minimising Monte-Carlo SURE (module doc) and bookkeeping for the record.

    Args:
        solve: ``(y, λ) ↦ x``, the regularised solver on measurements ``y``.
        forward: ``x ↦ A x``, the measurement operator.
        y: ``(m,)`` measurements, noise σ each.
        sigma: their noise standard deviation (> 0).
        sigma_px: the pixel noise of the least-squares image; the search bracket's unit.
        seed: seed of the Monte-Carlo probe ``b``.
        xatol: tolerance of the search on ``ln λ``.
    """
    b = np.random.default_rng(seed).standard_normal(y.size)
    eps = SURE_EPS * sigma
    m = y.size

    def risk(log_lam: float) -> float:
        lam = float(np.exp(log_lam))
        f0 = forward(solve(y, lam).ravel())
        f1 = forward(solve(y + eps * b, lam).ravel())
        div = float(b @ (f1 - f0)) / eps
        return float(np.sum((y - f0) ** 2) - m * sigma**2 + 2.0 * sigma**2 * div)

    lo, hi = (np.log(f * sigma_px) for f in SURE_BRACKET)
    res = minimize_scalar(risk, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
    lam = float(np.exp(res.x))
    return lam, {"sure": float(res.fun) / m, "sure_evaluations": int(res.nfev)}
