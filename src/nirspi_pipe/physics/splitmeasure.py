"""The split Hadamard measurement (Eq. 1): the noise-free readings of each split pattern pair
(:func:`split_measure`), and the same when the attenuation changes per reading
(:func:`modulated_split`, a fog that fluctuates during the acquisition), for all patterns at once
by the fast Walsh-Hadamard transform. Moved out of ``physics/forward.py`` (now :mod:`nirspi_pipe.physics.stagetypes`; issue 42
item 5): the forward model's measurement step uses it, and so do the FSRCNN training data and the
device emulator.
"""

from __future__ import annotations

import math

import numpy as np

from nirspi_pipe.patterns.hadamard import fwht2

__all__ = ["modulated_split", "split_measure"]


def split_measure(radiance: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free split measurements of ``radiance`` for the given flat pattern indices.

    Pattern ``P_k`` (±1) is shown as ``(1 + P_k)/2`` and ``(1 − P_k)/2``; with ``c_k = Σ P_k O``
    (Eq. 1, α = 1) and ``S = Σ O`` the two readings are ``(S + c_k)/2`` and ``(S − c_k)/2``.
    Units: radiance × pixels. Cost ``O(N log N)`` for all patterns at once.
    """
    coeffs = fwht2(radiance).ravel()[np.asarray(indices, dtype=np.int64)]
    total = float(radiance.sum())
    return 0.5 * (total + coeffs), 0.5 * (total - coeffs)


def modulated_split(
    base: np.ndarray, x: np.ndarray, c_pos: np.ndarray, c_neg: np.ndarray, indices: np.ndarray, tol: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """Split readings of ``base ⊙ exp(−c x)`` where the scalar ``c`` changes per reading.

    ``pos_k = Σ (1 + P_k)/2 ⊙ base ⊙ e^{−c_pos[k] x}``, ``neg_k`` likewise with ``(1 − P_k)/2``
    and ``c_neg[k]``. This is how a fog density that fluctuates during the acquisition
    (``β(t) = β f(t)``) acts on every pattern without building the patterns: around the
    base-weighted mean ``x₀``, ``e^{−c x} = e^{−c x₀} Σ_j (−c)^j (x − x₀)^j / j!``, one transform per
    term, truncated when the remainder bound is below ``tol`` (a handful of terms in practice).
    When ``|c (x − x₀)|`` exceeds 8 the series is replaced by exact transforms at 65 levels of
    ``c`` with linear interpolation between them.
    """
    idx = np.asarray(indices, dtype=np.int64)
    c_pos = np.asarray(c_pos, dtype=np.float64)
    c_neg = np.asarray(c_neg, dtype=np.float64)
    w = np.abs(base)
    x = np.where(w > 0, x, 0.0)
    x0 = float((w * x).sum() / w.sum()) if w.sum() > 0 else 0.0
    dx = np.where(w > 0, x - x0, 0.0)
    cmax = float(max(np.abs(c_pos).max(initial=0.0), np.abs(c_neg).max(initial=0.0)))
    amp = cmax * float(np.abs(dx).max(initial=0.0))
    if amp <= 8.0:
        pos = np.zeros(idx.size)
        neg = np.zeros(idx.size)
        term = base.astype(np.float64)
        w_pos = np.ones(idx.size)  # (−c)^j, updated in place
        w_neg = np.ones(idx.size)
        j = 0
        while True:
            f = fwht2(term).ravel()[idx]
            s = float(term.sum())
            pos += w_pos * (s + f)
            neg += w_neg * (s - f)
            bound = amp ** (j + 1) / math.factorial(j + 1) * math.exp(amp)
            if bound < tol or j >= 60:
                break
            j += 1
            term = term * dx / j
            w_pos *= -c_pos
            w_neg *= -c_neg
        pos *= 0.5
        neg *= 0.5
        return pos * np.exp(-c_pos * x0), neg * np.exp(-c_neg * x0)
    both = np.concatenate([c_pos, c_neg])
    levels = np.linspace(both.min(), both.max(), 65)
    f_lv = np.empty((levels.size, idx.size))
    s_lv = np.empty(levels.size)
    for i, c in enumerate(levels):
        img = base * np.exp(-c * x)
        f_lv[i] = fwht2(img).ravel()[idx]
        s_lv[i] = img.sum()

    def interp(c: np.ndarray, sign: float) -> np.ndarray:
        pos_in = np.clip(np.searchsorted(levels, c) - 1, 0, levels.size - 2)
        t = (c - levels[pos_in]) / np.maximum(levels[pos_in + 1] - levels[pos_in], 1e-300)
        k = np.arange(idx.size)
        lo = 0.5 * (s_lv[pos_in] + sign * f_lv[pos_in, k])
        hi = 0.5 * (s_lv[pos_in + 1] + sign * f_lv[pos_in + 1, k])
        return (1 - t) * lo + t * hi

    return interp(c_pos, 1.0), interp(c_neg, -1.0)
