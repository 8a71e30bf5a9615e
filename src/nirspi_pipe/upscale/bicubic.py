"""Upscale ``bicubic``: cubic-spline interpolation (scipy ``ndimage.zoom``, order 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from nirspi_pipe.types import Image2D
from nirspi_pipe.upscale.base import as_finite_image, check_scale, finish

__all__ = ["bicubic", "Bicubic"]


def bicubic(image: np.ndarray, scale: int) -> np.ndarray:
    """Upscale a 2D image ``scale`` times by cubic B-spline interpolation.

    ``grid_mode=True`` aligns pixel areas (low-res pixel ``i`` ↔ high-res pixels ``i·s … i·s+s−1``,
    sample position ``(j + ½)/s − ½`` in low-res pixels), and ``mode="reflect"`` mirrors about
    the image edge (half-sample symmetric), so a constant image stays constant. The output is
    exactly ``(h·s, w·s)``. Units: those of ``image``.
    """
    x = np.asarray(image, dtype=np.float64)
    out = ndimage.zoom(x, scale, order=3, mode="reflect", grid_mode=True)
    assert out.shape == (x.shape[0] * scale, x.shape[1] * scale)
    return out


@dataclass(frozen=True)
class Bicubic:
    """Upscale ``bicubic``: the interpolation baseline FSRCNN is compared against.

    Attributes:
        scale: upscaling factor, 2, 3 or 4.
        clip: clip the result to [0, 1] (cubic interpolation overshoots at edges).
    """

    scale: int = 2
    clip: bool = True

    def __post_init__(self) -> None:
        check_scale(self.scale)

    def upscale(self, image: Image2D) -> Image2D:
        x = as_finite_image(image.data, "bicubic")
        y = finish(bicubic(x, int(self.scale)), self.clip)
        return Image2D(y, info={"model": "bicubic", "scale": int(self.scale), "shape": list(y.shape)})
