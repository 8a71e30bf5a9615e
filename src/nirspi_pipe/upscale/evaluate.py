"""Held-out scores of FSRCNN against bicubic (PSNR and SSIM from scikit-image, data range 1).

Both upscalers get the same SPI reconstruction (:func:`nirspi_pipe.upscale.data.heldout_pairs`)
and are scored against the high-resolution true radiance over the whole image, after clipping
to [0, 1] as the ``upscale`` stages do by default.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nirspi_pipe.metrics import psnr, ssim
from nirspi_pipe.upscale.base import finish
from nirspi_pipe.upscale.bicubic import bicubic
from nirspi_pipe.upscale.data import heldout_pairs
from nirspi_pipe.upscale.fsrcnn import FsrcnnWeights, fsrcnn_forward

__all__ = ["score_heldout", "summarise"]


def score_heldout(
    weights: FsrcnnWeights, noise_rels: tuple[float, ...] = (0.0, 1e-3), n_lr: int = 64
) -> list[dict[str, Any]]:
    """One row per held-out image and noise level: ``psnr_bicubic``, ``psnr_fsrcnn`` (dB),
    ``ssim_bicubic``, ``ssim_fsrcnn`` and ``gain_db`` = fsrcnn − bicubic PSNR."""
    rows = []
    for noise_rel in noise_rels:
        for pair in heldout_pairs(weights.scale, noise_rel, n_lr=n_lr):
            bic = finish(bicubic(pair.lr, weights.scale), True)
            net = finish(fsrcnn_forward(pair.lr, weights), True)
            row: dict[str, Any] = {
                "scale": weights.scale,
                "noise_rel": noise_rel,
                "image": pair.name,
                "psnr_bicubic": psnr(pair.hr, bic),
                "psnr_fsrcnn": psnr(pair.hr, net),
                "ssim_bicubic": ssim(pair.hr, bic),
                "ssim_fsrcnn": ssim(pair.hr, net),
            }
            row["gain_db"] = row["psnr_fsrcnn"] - row["psnr_bicubic"]
            rows.append(row)
    return rows


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean of each score per (scale, noise_rel), with the number of images."""
    keys = sorted({(r["scale"], r["noise_rel"]) for r in rows})
    out = []
    for scale, noise in keys:
        sel = [r for r in rows if r["scale"] == scale and r["noise_rel"] == noise]
        mean = {
            k: float(np.mean([r[k] for r in sel]))
            for k in ("psnr_bicubic", "psnr_fsrcnn", "ssim_bicubic", "ssim_fsrcnn", "gain_db")
        }
        out.append({"scale": scale, "noise_rel": noise, "images": len(sel), **mean})
    return out
