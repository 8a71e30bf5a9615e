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

__all__ = ["REASONS", "SECTIONS", "drop_nonfinite", "is_finite_tree"]

#: The record sections that hold results (``config`` is the user's input, ``meta`` bookkeeping).
SECTIONS = ("metrics", "derived", "timings_ms", "info")

#: Known causes, by the last part of the key.
REASONS = {
    "ssim": "SSIM is undefined for images smaller than 3x3 pixels (scikit-image needs an odd window >= 3; "
    "the paper's SSIM uses 7x7)",
    "psnr": "PSNR is infinite when the reconstruction equals the ground truth exactly (RMSE 0)",
}


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


def _scrub(node: MutableMapping[str, Any], path: str, out: list[str]) -> None:
    for key in list(node):
        value = node[key]
        where = f"{path}.{key}"
        if isinstance(value, MutableMapping):
            _scrub(value, where, out)
        elif not is_finite_tree(value):
            del node[key]
            reason = REASONS.get(str(key).split(".")[-1].split("_")[0], "not a finite number")
            out.append(f"{sanitize_text(where, 120)}={_describe(value)} left out of the record: {reason}")


def drop_nonfinite(record: MutableMapping[str, Any]) -> list[str]:
    """Remove non-finite numbers from the result sections of ``record`` (in place) and return
    one warning line per removed value (``metrics.ssim=nan left out of the record: ...``)."""
    out: list[str] = []
    for section in SECTIONS:
        node = record.get(section)
        if isinstance(node, MutableMapping):
            _scrub(node, section, out)
    return out
