"""Image and depth metrics.

SSIM and PSNR come from scikit-image; RMSE is the paper's Eq. (16). Images are relative
radiance in [0, 1], so ``data_range = 1``.

Two scores per image metric (docs/paper.md, "Metrics"):

* ``psnr``, ``ssim`` — **normalised**, as the single-pixel-imaging literature reports them: the
  reference is the noise-free image of the same camera in the same condition
  (``Acquisition.reference``: fall-off, fog transmission and veil included; the truth's radiance
  when a source gives none), scaled so that its peak is 1; the reconstruction is mapped onto it
  by the least-squares gain and offset (:func:`fit_gain_offset`), then scored with data range 1.
  A noise-free reconstruction scores at least 100 dB in every condition (fog included); PSNR is
  capped at :data:`PSNR_CAP_DB` so that records stay finite.
* ``psnr_raw``, ``ssim_raw`` — **radiometric**: the raw reconstruction against the clear-air
  radiance, data range 1 (the gain of clear air at the nominal distance is kept, so fog and
  fall-off count as errors).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.stages import Products

__all__ = [
    "DEGENERATE_FLAG",
    "PSNR_CAP_DB",
    "ImageMetrics",
    "degenerate_reference",
    "fit_gain_offset",
    "normalised_pair",
    "psnr",
    "rmse",
    "ssim",
]

_IMAGE_METRICS = ("ssim", "psnr", "rmse")

#: Normalised PSNR is capped here (dB): float64 rounding of a noise-free fit lies far above it,
#: and an infinite value would not survive the records' no-NaN/no-inf rule.
PSNR_CAP_DB = 200.0

#: A reference (the noise-free image the normalised scores fit to) is **degenerate** when its
#: contrast ``(max − min) / max`` is below this: the gain-and-offset fit then maps any image onto
#: a near-constant, and PSNR/SSIM say "perfect" for an image with no object in it (issue 32).
#: Assumed: one part per million, 15 times below one step of a 16-bit ADC (1/65536).
DEGENERATE_CONTRAST = 1e-6
#: ... or when its peak is below this, in relative radiance (white target at the nominal distance
#: = 1). Assumed: 1e-12 of a white target is far below one photon per pattern for the photon
#: budgets the simulator models (Table 1), so nothing of the object reaches the detector.
DEGENERATE_PEAK = 1e-12
#: The flag a degenerate reference leaves in the metrics (1.0) instead of ``psnr``/``ssim``.
DEGENERATE_FLAG = "degenerate_reference"


def degenerate_reference(reference: np.ndarray) -> str | None:
    """Why the normalised scores are undefined for ``reference`` (one phrase), or None."""
    ref = np.asarray(reference, dtype=np.float64)
    if ref.size == 0 or not np.all(np.isfinite(ref)):
        return "the reference image is empty or not finite"
    peak, low = float(ref.max()), float(ref.min())
    if not peak > DEGENERATE_PEAK:
        return f"the reference image is dark (peak {peak:.3g} of a white target; nothing of the object arrives)"
    if (peak - low) / peak < DEGENERATE_CONTRAST:
        return f"the reference image is uniform (contrast {(peak - low) / peak:.2g}; no object is visible)"
    return None


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root-mean-square error over all ``M × N`` entries, Eq. (16). Units of the inputs."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def psnr(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (scikit-image); ``inf`` for an exact reconstruction."""
    # start-up: loads scipy, skimage, charset_normalizer (250 ms here)
    from skimage.metrics import (
        peak_signal_noise_ratio,
    )

    if rmse(truth, estimate) == 0.0:
        return float("inf")
    return float(peak_signal_noise_ratio(truth, estimate, data_range=data_range))


def ssim(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (scikit-image, 7×7 Gaussian-free window; smaller for tiny images)."""
    side = min(truth.shape)
    win = min(7, side if side % 2 == 1 else side - 1)
    if win < 3:
        return float("nan")
    # start-up: loads scipy, skimage, charset_normalizer (250 ms here)
    from skimage.metrics import (
        structural_similarity,
    )

    return float(structural_similarity(truth, estimate, data_range=data_range, win_size=win))


def fit_gain_offset(reference: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """Least-squares gain ``a`` and offset ``b`` minimising ``‖a·estimate + b − reference‖²``.

    A constant estimate gets ``a = 0`` and ``b = mean(reference)``. Dimensionless gain; offset
    in the reference's units."""
    x = np.asarray(estimate, dtype=np.float64).ravel()
    y = np.asarray(reference, dtype=np.float64).ravel()
    xc = x - x.mean()
    var = float(xc @ xc)
    if not var > 0:
        return 0.0, float(y.mean())
    a = float(xc @ (y - y.mean())) / var
    return a, float(y.mean() - a * x.mean())


def normalised_pair(reference: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference scaled to peak 1 and the estimate mapped onto it by :func:`fit_gain_offset`.
    A reference without a positive peak is left unscaled."""
    ref = np.asarray(reference, dtype=np.float64)
    peak = float(np.max(ref)) if ref.size else 0.0
    if peak > 0:
        ref = ref / peak
    a, b = fit_gain_offset(ref, estimate)
    return ref, a * np.asarray(estimate, dtype=np.float64) + b


def _psnr_normalised(ref: np.ndarray, est: np.ndarray) -> float:
    err = rmse(ref, est)
    if err == 0.0:
        return PSNR_CAP_DB
    return float(min(PSNR_CAP_DB, -20.0 * np.log10(err)))


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics ``default``: SSIM, PSNR (dB) and RMSE of the 2D reconstruction (module docstring):
    ``ssim``/``psnr`` normalised, ``ssim_raw``/``psnr_raw`` radiometric, ``rmse`` (Eq. 16) raw
    against the ground-truth radiance (relative, data range 1).

    Attributes:
        names: which of ``ssim``, ``psnr``, ``rmse`` to compute.
        clip: clip the reconstruction to [0, 1] before the raw scores (a physical image cannot
            leave it).
    """

    names: tuple[str, ...] = field(default=_IMAGE_METRICS)
    clip: bool = False

    def __post_init__(self) -> None:
        bad = [n for n in self.names if n not in _IMAGE_METRICS]
        if bad:
            raise ConfigError("names", list(self.names), f"a subset of {list(_IMAGE_METRICS)}")
        # scikit-image's metric functions bring scipy.stats, 0.7 s (python -X importtime -c "from
        # skimage.metrics import structural_similarity"): loaded when a metrics stage is built, so
        # that composing a config (which imports this module for its defaults) does not pay it and
        # the first job's timed metrics stage does not either
        self.warm_up({})

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Import scikit-image's metric functions (0.7 s with scipy.stats;
        :class:`nirspi_pipe.stages.WarmsUp`)."""
        # warm-up: loads scipy, skimage, charset_normalizer (250 ms here), before jobs fork
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity  # noqa: F401

    def compute(self, products: Products) -> dict[str, float]:
        truth = products.truth
        if truth is None:
            warnings.warn("metrics: no ground truth in this acquisition; nothing to score", stacklevel=2)
            return {}
        est = np.asarray(products.image.data, dtype=np.float64)
        reference = products.acquisition.reference
        return self.score(truth.radiance, est, reference)

    def score(
        self, truth: np.ndarray, estimate: np.ndarray, reference: np.ndarray | None = None, prefix: str = ""
    ) -> dict[str, float]:
        """The scores of ``estimate`` against ``truth`` (raw) and ``reference`` (normalised; the
        truth when None), keys prefixed by ``prefix``."""
        est = np.asarray(estimate, dtype=np.float64)
        ref = np.asarray(truth, dtype=np.float64)
        if est.shape != ref.shape:
            raise ValueError(f"reconstruction {est.shape} and ground truth {ref.shape} differ in shape")
        norm_ref = ref if reference is None else np.asarray(reference, dtype=np.float64)
        if norm_ref.shape != est.shape:
            raise ValueError(f"reconstruction {est.shape} and reference {norm_ref.shape} differ in shape")
        why = degenerate_reference(norm_ref)
        if why is not None:
            warnings.warn(
                f"metrics: {why}, so the normalised {prefix}psnr/{prefix}ssim are undefined and left out "
                f"({prefix}{DEGENERATE_FLAG}=1); the raw scores ({prefix}psnr_raw, {prefix}ssim_raw, {prefix}rmse) are kept",
                stacklevel=2,
            )
        nref, nest = normalised_pair(norm_ref, est)
        raw_est = np.clip(est, 0.0, 1.0) if self.clip else est
        out: dict[str, float] = {}
        for name in self.names:
            if name == "rmse":
                out[f"{prefix}rmse"] = rmse(ref, raw_est)
            elif name == "psnr":
                if why is None:
                    out[f"{prefix}psnr"] = _psnr_normalised(nref, nest)
                out[f"{prefix}psnr_raw"] = psnr(ref, raw_est)
            else:
                if why is None:
                    out[f"{prefix}ssim"] = ssim(nref, nest)
                out[f"{prefix}ssim_raw"] = ssim(ref, raw_est)
        if why is not None:
            out[f"{prefix}{DEGENERATE_FLAG}"] = 1.0
        return out
