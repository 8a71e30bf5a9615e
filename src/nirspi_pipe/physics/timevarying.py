"""Time-varying effects over an acquisition: background drift/flicker and fog fluctuation.

Every reading has its own time stamp (the two halves of a split pair are taken one pattern
period apart), so a background that changes no longer cancels exactly in ``y_pos − y_neg``, and
a fog whose density changes weighs early and late patterns differently. That is what makes the
scan order matter at 100 % sampling (DESIGN §3).

All functions take an explicit ``numpy.random.Generator``; factors are multiplicative and
dimensionless, and never negative.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ornstein_uhlenbeck", "background_factor", "fog_factor"]


def ornstein_uhlenbeck(times_s: np.ndarray, std: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary Ornstein–Uhlenbeck samples at sorted or unsorted ``times_s`` (s).

    Zero mean, standard deviation ``std`` and correlation ``exp(−|Δt|/tau_s)``; sampled exactly
    (no discretisation error) in time order. ``std = 0`` gives zeros without drawing.
    """
    t = np.asarray(times_s, dtype=np.float64)
    if std <= 0 or t.size == 0:
        return np.zeros(t.shape)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    with np.errstate(over="ignore"):  # Δt/τ beyond float64: uncorrelated steps, exp(−inf) = 0
        a = np.exp(-np.diff(ts) / tau_s)
    z = rng.standard_normal(ts.size)
    innov = std * np.sqrt(np.maximum(1.0 - a * a, 0.0)) * z[1:]
    if a.size and np.allclose(a, a[0], rtol=1e-12, atol=0.0):
        # uniform steps: x_i = Σ_j a^{i−j} drive_j, by a log-step (Hillis–Steele) scan
        x = np.concatenate([[std * z[0]], innov])
        shift, coef = 1, float(a[0])
        while shift < x.size and coef > 0.0:
            x[shift:] = x[shift:] + coef * x[:-shift].copy()
            shift, coef = 2 * shift, coef * coef
    else:
        x = np.empty(ts.size)
        x[0] = std * z[0]
        for i in range(1, ts.size):  # the same recursion with varying steps
            x[i] = a[i - 1] * x[i - 1] + innov[i - 1]
    out = np.empty_like(x)
    out[order] = x
    return out


def background_factor(
    times_s: np.ndarray,
    rng: np.random.Generator,
    drift_rel_per_s: float = 0.0,
    flicker_rel: float = 0.0,
    flicker_hz: float = 100.0,
    wander_rel: float = 0.0,
    wander_time_s: float = 0.1,
) -> np.ndarray:
    """Relative background level at ``times_s``: ``1 + drift·t + flicker·sin(2πft + φ) + OU``,
    floored at 0. The flicker phase φ is drawn from ``rng`` (seeded)."""
    t = np.asarray(times_s, dtype=np.float64)
    f = 1.0 + drift_rel_per_s * t
    if flicker_rel:
        phase = rng.uniform(0.0, 2 * np.pi)
        f = f + flicker_rel * np.sin(2 * np.pi * flicker_hz * t + phase)
    if wander_rel:
        f = f + ornstein_uhlenbeck(t, wander_rel, wander_time_s, rng)
    return np.maximum(f, 0.0)


def fog_factor(times_s: np.ndarray, rng: np.random.Generator, rel: float, tau_s: float) -> np.ndarray:
    """Relative fog density (so β(t) = β · factor) at ``times_s``: ``1 + OU``, floored at 0."""
    return np.maximum(1.0 + ornstein_uhlenbeck(times_s, rel, tau_s, rng), 0.0)
