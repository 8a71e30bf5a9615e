"""The TV weight of an undersampled acquisition, chosen from its own measurements (hold-out).

Undersampled (``m < N``), SURE on the measured coefficients (:mod:`nirspi_pipe.solvers.noise`)
cannot see the ``N − m`` unmeasured ones that the TV prior fills in, and noise-free data give it
nothing to estimate at all (σ = 0). We estimate the image's squared error in the Hadamard domain
(``‖A_full (x − x_true)‖² = N ‖x − x_true‖²``, the transform being orthogonal up to ``N``) as the
error on the measured coefficients plus the error on the unmeasured ones:

* every 10th non-zero measurement in acquisition order (``HOLDOUT_STRIDE``, from the 6th on, so
  DC and the first measurements stay in; :func:`holdout`) is held out, set ``H``; the others are
  the training set ``T``;
* for each λ of a grid (``λ = 0``, the zero-filled least-squares image, and ``GRID_POINTS`` weights
  spaced logarithmically), FISTA-TV is fitted on ``T`` (all λ at once, as one batch, warm TV duals);
* measured part: the training residual ``‖A_T x_λ − y_T‖²`` (exact for exact data); with noise σ,
  Stein's correction ``− |T|σ² + 2σ² div`` (one Monte-Carlo probe, Ramani, Blu & Unser 2008, one
  more batched fit), i.e. SURE on ``T``;
* unmeasured part: the held-out prediction error ``‖A_H x_λ − y_H‖² − |H|σ²`` (the cross-validation
  estimate of the error of a coefficient the fit did not see; Stone 1974), scaled to the
  ``N − m`` unmeasured coefficients by ``(N − m)/|H|``;
* λ minimises the sum (``score``, divided by ``N²``: an estimate of the image's mean squared
  error); the solver then refits on all measurements, warm-started from the chosen fit.

The held-out coefficients are interleaved with the measured set (a stride), not the tail of the
order (the next coefficients an order would measure): on the checkerboard at 25 %, zig-zag, the tail
picked λ = 0 (30.8 dB) against 34.0 dB for the stride's choice; and the held-out error alone, without
the training residual, picked λ ≫ the best on grass (24.3 against 26.7 dB with the stride; with the
tail also on brick and gravel, 2–4 dB below). Both were trials while
writing this rule (issue 26), not kept; the kept rule's results are in docs/reconstruction.md
(``python experiments/heldout/heldout_cs.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = [
    "HOLDOUT_STRIDE",
    "HOLDOUT_START",
    "GRID_POINTS",
    "GRID_SPAN",
    "MIN_MEASUREMENTS",
    "CV_MAX_ITER",
    "CV_TV_ITER",
    "holdout",
    "weight_grid",
    "cv_weight",
]

#: One measurement in this many is held out (the brief's "fit on 90 %, score the other 10 %").
HOLDOUT_STRIDE = 10
#: Position of the first held-out measurement in acquisition order (DC, first, stays in the fit).
HOLDOUT_START = 5
#: Fewer measurements than this leave nothing to hold out: the rule falls back to ``lam_floor``.
MIN_MEASUREMENTS = HOLDOUT_START + 1
#: Non-zero weights in the grid (plus λ = 0).
GRID_POINTS = 7
#: The grid spans this factor, from ``hi / GRID_SPAN`` to ``hi``: with an rms level of 0.3–0.5,
#: about 1e-4 to 0.1. The best fixed weights at 25 %, noise-free, on the 15 held-out images are
#: 3e-5 to 1e-3 (``experiments/heldout/results/fixed.csv``; at 3e-5, brick and gravel, within
#: 0.01 dB of λ = 0, which is in the grid).
GRID_SPAN = 1000.0
#: Top of the grid in units of the image's rms level, and in units of the pixel noise σ_px. With
#: the device's noise (64², 10–25 %, clock/brick/coins/camera) the best fixed weight was 0.1
#: ≈ 0.4 σ_px; a top of 10 σ_px (SURE's bracket) let the short training fits rank 2.4 first on 51
#: of 360 noisy acquisitions, a flat image (7–9 dB against 17–22 dB for ``fwht``; issue 26's
#: first run of ``experiments/heldout/heldout_cs.py``).
GRID_TOP_RMS = 0.25
GRID_TOP_NOISE = 1.0
#: The fits on the training set stop after this many FISTA iterations, with this many inner TV
#: iterations each (the final fit on all measurements runs to the solver's own ``tol``): they rank
#: weights, they are not the image.
CV_MAX_ITER = 40
CV_TV_ITER = 5


def holdout(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(train, held)`` positions of the measurements ``y`` (module doc): every
    ``HOLDOUT_STRIDE``-th of those that are not exactly zero, from the ``HOLDOUT_START``-th on.

    Exact zeros (a symmetric scene's odd patterns, noise-free) are predicted exactly by every
    weight, λ = 0 included; held out, they made the score of λ = 0 zero (the sphere at 25 %,
    spiral: λ = 0, 33.5 dB, against 45.2 dB at λ = 0.003, ``tests/test_reconstruction_quality.py``)."""
    pos = np.arange(y.size)
    live = pos[np.abs(y) > 1e-12 * float(np.max(np.abs(y)))] if y.size and np.any(y) else pos
    held = live[HOLDOUT_START::HOLDOUT_STRIDE]
    return np.setdiff1d(pos, held), held


def weight_grid(rms: float, sigma_px: float) -> np.ndarray:
    """λ = 0 and ``GRID_POINTS`` weights from ``hi/GRID_SPAN`` to ``hi``,
    ``hi = max(GRID_TOP_RMS·rms, GRID_TOP_NOISE·σ_px)``, ascending."""
    hi = max(GRID_TOP_RMS * rms, GRID_TOP_NOISE * sigma_px)
    if not hi > 0:
        return np.zeros(1)
    return np.r_[0.0, np.geomspace(hi / GRID_SPAN, hi, GRID_POINTS)]


def cv_weight(
    fit: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    predict: Callable[[np.ndarray, np.ndarray], np.ndarray],
    y: np.ndarray,
    n_pixels: int,
    sigma: float,
    grid: np.ndarray,
    seed: int = 0,
    eps_rel: float = 0.01,
) -> tuple[int, np.ndarray, dict[str, float]]:
    """Index of the chosen weight in ``grid``, the fits on the training set, and the record.

    Args:
        fit: ``(rows, Y, lams) ↦ X``: FISTA-TV on the measurements at positions ``rows``, one
            fit per row of ``Y`` (``(B, |rows|)``) with weight ``lams[b]``; returns ``(B, n, n)``.
        predict: ``(X, rows) ↦ (B, |rows|)``, the measurements the images ``X`` predict at ``rows``.
        y: ``(m,)`` measurements; ``n_pixels``: ``N``; ``sigma``: their noise (0: exact).
        grid: the weights tried; ``eps_rel``: Monte-Carlo step in units of σ.
    """
    m = y.size
    train, held = holdout(y)
    if held.size == 0:
        train, held = holdout(np.ones(m))
    lams = np.asarray(grid, np.float64)
    y_t = y[train]
    x = fit(train, np.broadcast_to(y_t, (lams.size, y_t.size)), lams)
    res_t = np.sum((predict(x, train) - y_t) ** 2, axis=1)
    err_h = np.sum((predict(x, held) - y[held]) ** 2, axis=1) - held.size * sigma**2
    fits = 1
    if sigma > 0:
        b = np.random.default_rng(seed).standard_normal(y_t.size)
        eps = eps_rel * sigma
        x1 = fit(train, np.broadcast_to(y_t + eps * b, (lams.size, y_t.size)), lams)
        div = (predict(x1, train) - predict(x, train)) @ b / eps
        res_t = res_t - train.size * sigma**2 + 2.0 * sigma**2 * div
        fits = 2
    score = (res_t + err_h * (n_pixels - m) / held.size) / float(n_pixels) ** 2
    best = int(np.argmin(score))
    info = {
        "cv_score": float(score[best]),
        "cv_score_zero_filled": float(score[0]),
        "cv_held_out": int(held.size),
        "cv_grid_points": int(lams.size),
        "cv_grid_max": float(lams[-1]),
        "cv_fits": fits,
    }
    return best, x, info
