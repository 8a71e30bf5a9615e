"""Super-resolution of reconstructed images (config group ``upscale``).

``none`` (identity), ``bicubic`` (cubic-spline interpolation) and ``fsrcnn`` (FSRCNN, the
paper's CS-SRCNN step, numpy inference with shipped weights) at ×2, ×3 and ×4. See
``docs/upscale.md``.
"""

from nirspi_pipe.upscale.base import SCALES, block_mean
from nirspi_pipe.upscale.bicubic import Bicubic, bicubic
from nirspi_pipe.upscale.fsrcnn import FSRCNN, fsrcnn_forward, load_weights

__all__ = ["SCALES", "Bicubic", "FSRCNN", "bicubic", "block_mean", "fsrcnn_forward", "load_weights"]
