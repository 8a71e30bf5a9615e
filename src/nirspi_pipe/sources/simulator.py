"""Source ``simulator``: single-pixel measurement of a rendered scene.

This is the idealised detector: the 2D Hadamard patterns in the split convention, with optional
Gaussian detector noise. The physical model (fog, background light, photon budget, detector,
time-varying effects) builds on the same measurement in :mod:`nirspi_pipe.physics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.types import Acquisition, Scene

__all__ = ["Simulator", "split_measure"]


def split_measure(radiance: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free split measurements of ``radiance`` for the given flat pattern indices.

    Pattern ``P_k`` (±1) is shown as ``(1 + P_k)/2`` and ``(1 − P_k)/2``; with ``c_k = Σ P_k O``
    (Eq. 1, α = 1) and ``S = Σ O`` the two readings are ``(S + c_k)/2`` and ``(S − c_k)/2``.
    Units: radiance × pixels. Cost ``O(N log N)`` for all patterns at once.
    """
    coeffs = fwht2(radiance).ravel()[np.asarray(indices, dtype=np.int64)]
    total = float(radiance.sum())
    return 0.5 * (total + coeffs), 0.5 * (total - coeffs)


@dataclass(frozen=True)
class Simulator:
    """Simulated single-pixel camera with an ideal detector.

    Attributes:
        noise_rel: standard deviation of additive Gaussian detector noise on each reading,
            relative to the mean reading of a half pattern (``Σ radiance / 2``); 0 = noise-free.
        pattern_rate_hz: patterns shown per second (each ±1 measurement takes two), used for
            the timestamps.
    """

    noise_rel: float = 0.0
    pattern_rate_hz: float = 1000.0

    needs_scene = True

    def __post_init__(self) -> None:
        if not np.isfinite(self.noise_rel) or self.noise_rel < 0:
            raise ConfigError("noise_rel", self.noise_rel, "a relative noise level >= 0")
        if not self.pattern_rate_hz > 0:
            raise ConfigError("pattern_rate_hz", self.pattern_rate_hz, "a rate in Hz > 0")

    def acquire(
        self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator
    ) -> Acquisition:
        """Measure ``scene.radiance`` with the patterns ``indices``, in that order."""
        if scene is None:
            raise NirspiError("source=simulator needs a scene")
        if scene.radiance.shape != (n, n):
            raise NirspiError(f"scene rendered at {scene.radiance.shape}, patterns are {n}x{n}")
        y_pos, y_neg = split_measure(scene.radiance, indices)
        mean_reading = 0.5 * float(scene.radiance.sum())
        sigma = self.noise_rel * mean_reading
        if sigma > 0:
            y_pos = y_pos + rng.normal(0.0, sigma, y_pos.shape)
            y_neg = y_neg + rng.normal(0.0, sigma, y_neg.shape)
        m = len(indices)
        timestamps = np.arange(m) * (2.0 / self.pattern_rate_hz)
        signal_rms = float(np.sqrt(np.mean((y_pos - y_neg) ** 2))) if m else 0.0
        noise_rms = np.sqrt(2.0) * sigma
        snr_db = 20 * np.log10(signal_rms / noise_rms) if noise_rms > 0 and signal_rms > 0 else np.inf
        return Acquisition(
            n=n,
            indices=np.asarray(indices, dtype=np.int64),
            y_pos=y_pos,
            y_neg=y_neg,
            gain=1.0,
            truth=scene,
            timestamps_s=timestamps,
            derived={"snr_db": float(snr_db), "noise_sigma": float(sigma)},
            info={"patterns_measured": m, "patterns_shown": 2 * m},
        )
