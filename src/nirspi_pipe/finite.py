"""No NaN or Inf in a record with status ok (docs/hostile.md).

A run that succeeds may still produce a value that is not a number: SSIM of a 2×2 image, PSNR
of an exact reconstruction, a solver residual of an overflowing input. A record must not carry
such a value as if it were a result, so :func:`drop_nonfinite` removes every non-finite number
from a record's ``metrics``, ``derived``, ``timings_ms`` and ``info`` and returns one warning per
value saying what was left out and why. The runner calls it once, just before the record is
written (:func:`nirspi_pipe.execute.execute_job`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, MutableMapping
from typing import Any

import numpy as np

from nirspi_pipe.safeio import sanitize_text

__all__ = ["SECTIONS", "SSIM_MIN_SIDE", "drop_nonfinite", "is_finite_tree", "reason_for"]

#: The record sections that hold results (``config`` is the user's input, ``meta`` bookkeeping).
SECTIONS = ("metrics", "derived", "timings_ms", "info")

#: Below this side (pixels) SSIM has no window: scikit-image needs an odd window >= 3 (the paper's
#: SSIM uses 7x7), so :func:`nirspi_pipe.metrics.ssim` returns NaN for it.
SSIM_MIN_SIDE = 3

#: The phrase for an SSIM left out because the image is too small for its window (test_hostile_records).
SSIM_WINDOW = "SSIM is undefined for images smaller than 3x3 pixels (scikit-image needs an odd window >= 3; the paper's SSIM uses 7x7)"


def _kind(key: str) -> str | None:
    """Which score a metric key holds (``upscale_psnr_raw`` → ``psnr``), or None."""
    parts = str(key).split("_")
    for kind in ("psnr", "ssim", "rmse"):
        if kind in parts:
            return kind
    return None


def _side_of(key: str, sides: Mapping[str, int] | None) -> int | None:
    """The side (pixels) of the image a metric key scores: the camera image for an unprefixed
    key (``ssim_raw``), the image named by the prefix otherwise (``upscale_ssim`` → ``upscale``);
    None when ``sides`` does not say."""
    if not sides:
        return None
    prefix = str(key).split("_")[0]
    if _kind(prefix) is not None:  # no prefix: the camera image
        return sides.get("")
    return sides.get(prefix, min(sides.values()) if min(sides.values()) >= SSIM_MIN_SIDE else None)


def reason_for(key: str, value: Any, sides: Mapping[str, int] | None = None) -> str:
    """Why ``value`` (non-finite) under ``key`` is not a number, from the value itself and the
    sides of the images the run made (``sides``: ``""`` the camera image, ``"upscale"`` the
    upscaled one). Says only what the value and the sides show; otherwise "not a finite number"."""
    if not isinstance(value, (float, np.floating)):
        return "not a finite number"
    x, kind = float(value), _kind(str(key))
    if kind == "psnr":
        if x == math.inf:
            return "PSNR is +inf when the image equals its reference exactly (RMSE 0)"
        if x == -math.inf:
            return "PSNR is -inf when the error is infinite (the squared error overflowed float64: the image is far off its reference)"
        return "PSNR is NaN when the image or its reference holds NaN or Inf"
    if kind == "ssim":
        side = _side_of(str(key), sides)
        if side is not None and side < SSIM_MIN_SIDE:
            return f"{SSIM_WINDOW}; this image is {side}x{side}"
        if side is not None:
            return (
                f"SSIM is NaN on this {side}x{side} image (large enough for its window): the image or its "
                "reference holds NaN or Inf, or their squares overflowed float64"
            )
        return "SSIM is NaN: the image is smaller than its 3x3 window, or it holds NaN or Inf, or its squares overflowed float64"
    if kind == "rmse":
        if x == math.inf:
            return "RMSE is +inf when the squared error overflows float64 (the image is far off its reference)"
        return "RMSE is NaN when the image or its reference holds NaN or Inf"
    return "not a finite number"


def _bad_leaf(value: Any) -> bool:
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (float, np.floating)):
        return not math.isfinite(float(value))
    if isinstance(value, np.ndarray) and value.dtype.kind in "fc":
        return not bool(np.all(np.isfinite(value)))
    return False


def is_finite_tree(value: Any) -> bool:
    """True when no number anywhere in ``value`` (nested dicts, lists, arrays) is NaN or Inf."""
    if isinstance(value, Mapping):
        return all(is_finite_tree(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(is_finite_tree(v) for v in value)
    return not _bad_leaf(value)


def _describe(value: Any) -> str:
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return "a sequence holding NaN or Inf"


def _scrub(
    node: MutableMapping[str, Any], path: str, out: list[str], sides: Mapping[str, int] | None, scores: bool
) -> None:
    for key in list(node):
        value = node[key]
        where = f"{path}.{key}"
        if isinstance(value, MutableMapping):
            _scrub(value, where, out, sides, False)
        elif not is_finite_tree(value):
            del node[key]
            reason = reason_for(str(key), value, sides) if scores else "not a finite number"
            out.append(f"{sanitize_text(where, 120)}={_describe(value)} left out of the record: {reason}")


def drop_nonfinite(record: MutableMapping[str, Any], sides: Mapping[str, int] | None = None) -> list[str]:
    """Remove non-finite numbers from the result sections of ``record`` (in place) and return
    one warning line per removed value (``metrics.ssim_raw=nan left out of the record: ...``),
    its reason computed from the value (:func:`reason_for`; ``sides``: the sides in pixels of
    the run's images, ``""`` the camera image, ``"upscale"`` the upscaled one)."""
    out: list[str] = []
    for section in SECTIONS:
        node = record.get(section)
        if isinstance(node, MutableMapping):
            _scrub(node, section, out, sides, section == "metrics")
    return out
