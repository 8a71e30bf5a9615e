"""Image and depth metrics.

SSIM and PSNR come from scikit-image; RMSE is the paper's Eq. (16). Images are relative
radiance in [0, 1], so ``data_range = 1``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.stages import Products

__all__ = ["rmse", "psnr", "ssim", "ImageMetrics"]

_IMAGE_METRICS = ("ssim", "psnr", "rmse")


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root-mean-square error over all ``M × N`` entries, Eq. (16). Units of the inputs."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def psnr(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (scikit-image); ``inf`` for an exact reconstruction."""
    if rmse(truth, estimate) == 0.0:
        return float("inf")
    return float(peak_signal_noise_ratio(truth, estimate, data_range=data_range))


def ssim(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (scikit-image, 7×7 Gaussian-free window; smaller for tiny images)."""
    side = min(truth.shape)
    win = min(7, side if side % 2 == 1 else side - 1)
    if win < 3:
        return float("nan")
    return float(structural_similarity(truth, estimate, data_range=data_range, win_size=win))


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics ``default``: SSIM, PSNR (dB) and RMSE of the 2D reconstruction against the
    ground-truth radiance (relative, data range 1).

    Attributes:
        names: which of ``ssim``, ``psnr``, ``rmse`` to compute.
        clip: clip the reconstruction to [0, 1] before scoring (a physical image cannot leave it).
    """

    names: tuple[str, ...] = field(default=_IMAGE_METRICS)
    clip: bool = False

    def __post_init__(self) -> None:
        bad = [n for n in self.names if n not in _IMAGE_METRICS]
        if bad:
            raise ConfigError("names", list(self.names), f"a subset of {list(_IMAGE_METRICS)}")

    def compute(self, products: Products) -> dict[str, float]:
        truth = products.truth
        if truth is None:
            warnings.warn("metrics: no ground truth in this acquisition; nothing to score", stacklevel=2)
            return {}
        est = np.asarray(products.image.data, dtype=np.float64)
        ref = truth.radiance
        if est.shape != ref.shape:
            raise ValueError(f"reconstruction {est.shape} and ground truth {ref.shape} differ in shape")
        if self.clip:
            est = np.clip(est, 0.0, 1.0)
        funcs = {"ssim": ssim, "psnr": psnr, "rmse": rmse}
        return {name: funcs[name](ref, est) for name in self.names}
