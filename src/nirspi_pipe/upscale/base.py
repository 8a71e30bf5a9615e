"""Shared pieces of the ``upscale`` stages: scale validation, input checks and the identity.

Images are relative radiance (dimensionless, nominally in [0, 1]). The upscaled grid is aligned
on pixel *areas*: low-resolution pixel ``i`` covers high-resolution pixels ``i·s … i·s + s − 1``,
so its centre sits at high-resolution coordinate ``i·s + (s − 1)/2``. A camera pixel integrates
the radiance over its area, so the low-resolution image is the ``s × s`` block mean of the
high-resolution one (:func:`block_mean`), which is how the training and evaluation data are made.
"""

from __future__ import annotations

import warnings

import numpy as np

from nirspi_pipe.errors import ConfigError

__all__ = ["SCALES", "check_scale", "as_finite_image", "finish", "block_mean"]

#: Supported upscaling factors (the paper's FSRCNN step; Dong et al. 2016 train ×2, ×3, ×4).
SCALES = (2, 3, 4)


def check_scale(scale: object) -> int:
    """Return ``scale`` as an int, or raise :class:`ConfigError` on key ``scale``."""
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or int(scale) not in SCALES:
        raise ConfigError("scale", scale, "2, 3 or 4")
    return int(scale)


def as_finite_image(data: np.ndarray, stage: str) -> np.ndarray:
    """``data`` as a float64 2D array; non-finite pixels are replaced by 0 with a warning.

    Raises ValueError for an array that is not 2D or is empty.
    """
    x = np.asarray(data, dtype=np.float64)
    if x.ndim != 2 or x.size == 0:
        raise ValueError(f"upscale={stage}: expected a non-empty 2D image, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        warnings.warn(f"upscale={stage}: non-finite input pixels were replaced by 0", stacklevel=3)
        x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    return x


def finish(y: np.ndarray, clip: bool) -> np.ndarray:
    """Clip an upscaled image to the physical radiance range [0, 1] when ``clip`` is set."""
    return np.clip(y, 0.0, 1.0) if clip else y


def block_mean(hr: np.ndarray, scale: int) -> np.ndarray:
    """Area-average an ``(h·s, w·s)`` image into ``(h, w)`` pixels: what a camera pixel ``s``
    times larger integrates (relative radiance in, relative radiance out)."""
    h, w = hr.shape[0] // scale, hr.shape[1] // scale
    return hr[: h * scale, : w * scale].reshape(h, scale, w, scale).mean(axis=(1, 3))
