"""What every solver shares: checked measurements, fast linear operators, stopping records.

Measurement checks (:func:`checked_coefficients`) never change finite data; they warn, with
``warnings.warn``, where the reconstruction will be meaningless:

* all measurements zero (no signal): the image is blank;
* only the DC pattern measured: the image is a flat field at the mean radiance;
* a measurement larger than any non-negative scene can give (a saturated or corrupted
  pattern): ``|c_k| ≤ c_0`` for the ±1 Hadamard patterns when the DC reading ``c_0`` is known,
  and ``|c_k| ≤ Σ|P_k|`` (radiance ≤ 1) otherwise;
* non-finite measurements, which are replaced by 0 (the only change made).

Operators (:func:`measurement_operator`) are ``scipy.sparse.linalg.LinearOperator`` of shape
``(m, N)``: on the Hadamard path ``x ↦ (H_N x)[indices]`` and its adjoint by the fast transform
(``O(N log N)``, never an ``N × N`` matrix); with explicit patterns the ``(m, N)`` matrix itself.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.sparse.linalg import LinearOperator, aslinearoperator

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.patterns.hadamard import fwht
from nirspi_pipe.types import Acquisition

__all__ = [
    "checked_coefficients",
    "hadamard_operator",
    "measurement_operator",
    "require_hadamard",
    "relative_residual",
    "data_scale",
    "SATURATION_MARGIN",
    "TIE_RTOL",
]

#: A reading more than this factor above the physical bound is flagged as saturated.
SATURATION_MARGIN = 1.5


def checked_coefficients(acquisition: Acquisition, solver: str) -> np.ndarray:
    """The calibrated ±1 measurements (relative radiance × pixels), checked; see module doc."""
    c = np.asarray(acquisition.coefficients(), dtype=np.float64)
    if c.shape != (len(acquisition.indices),):
        raise NirspiError(f"solver={solver}: {c.size} measurements for {len(acquisition.indices)} patterns")
    if c.size == 0:
        raise NirspiError(f"solver={solver}: the acquisition has no measurements")
    bad = ~np.isfinite(c)
    if bad.any():
        warnings.warn(f"{solver}: {int(bad.sum())} non-finite measurement(s) replaced by 0", stacklevel=3)
        c = np.where(bad, 0.0, c)
    if not np.any(c):
        warnings.warn(
            f"{solver}: all {c.size} measurements are zero (no signal); the image is blank and meaningless",
            stacklevel=3,
        )
        return c
    idx = np.asarray(acquisition.indices, dtype=np.int64)
    if acquisition.patterns is None:
        if np.all(idx == 0):
            warnings.warn(
                f"{solver}: only the DC pattern was measured (ratio {acquisition.ratio:.3g}); the "
                "image is a flat field at the mean radiance, with no spatial information",
                stacklevel=3,
            )
        dc = c[idx == 0]
        bound = abs(float(dc[0])) if dc.size else float(acquisition.n_pixels)
        bound_text = (
            "the DC reading (|c_k| <= c_0 for a non-negative scene)" if dc.size else ("n² (relative radiance <= 1)")
        )
        check = idx != 0
    else:
        bound_arr = np.abs(np.asarray(acquisition.patterns, dtype=np.float64)).sum(axis=1)
        bound = bound_arr
        bound_text = "Σ|P_k| (relative radiance <= 1)"
        check = np.ones(c.size, dtype=bool)
    over = check & (np.abs(c) > SATURATION_MARGIN * bound)
    if over.any():
        worst = int(np.argmax(np.where(over, np.abs(c), -np.inf)))
        saturated = acquisition.derived.get("saturated_patterns")
        if saturated:  # the source counted saturated readings: name them
            cause = f"saturated ({int(saturated)} readings at full scale) or corrupted"
        elif saturated == 0:  # counted, none: noise (e.g. dense fog) or a corrupted file
            cause = "no reading saturated, so noise (e.g. dense fog or strong background) or corruption"
        else:
            cause = "saturated or corrupted (or noise-dominated)"
        warnings.warn(
            f"{solver}: {int(over.sum())} measurement(s) exceed {bound_text} "
            f"(pattern {int(idx[worst])} reads {c[worst]:.3g}): {cause}; the image "
            "carries that pattern as an artefact and is not meaningful",
            stacklevel=3,
        )
    return c


def require_hadamard(acquisition: Acquisition, solver: str) -> None:
    """Raise a one-line :class:`NirspiError` when the acquisition has explicit patterns."""
    if acquisition.patterns is not None:
        raise NirspiError(
            f"solver={solver} needs a Hadamard acquisition; this one has explicit patterns "
            "(use solver=lstsq, solver=fista_tv or solver=correlation)"
        )


def hadamard_operator(n: int, indices: np.ndarray) -> LinearOperator:
    """The subsampled 2D Hadamard measurement ``x ↦ (H_{n²} x)[indices]`` as a LinearOperator
    ``(m, n²)`` with its adjoint ``r ↦ H_{n²} zero_fill(r)``; both ``O(N log N)``."""
    idx = np.asarray(indices, dtype=np.int64)
    size = n * n

    def matvec(x: np.ndarray) -> np.ndarray:
        return fwht(np.asarray(x, dtype=np.float64).reshape(size))[idx]

    def rmatvec(r: np.ndarray) -> np.ndarray:
        full = np.zeros(size)
        full[idx] = np.asarray(r, dtype=np.float64).reshape(idx.size)
        return fwht(full)

    return LinearOperator((idx.size, size), matvec=matvec, rmatvec=rmatvec, dtype=np.float64)


def measurement_operator(acquisition: Acquisition) -> LinearOperator:
    """The acquisition's linear operator ``(m, n²)``: the fast Hadamard one, or the explicit
    pattern matrix (rows = patterns, row-major pixels) wrapped as a LinearOperator."""
    if acquisition.patterns is None:
        return hadamard_operator(acquisition.n, acquisition.indices)
    p = np.asarray(acquisition.patterns, dtype=np.float64)
    if p.shape != (len(acquisition.indices), acquisition.n_pixels):
        raise NirspiError(
            f"explicit patterns have shape {p.shape}, expected ({len(acquisition.indices)}, {acquisition.n_pixels})"
        )
    return aslinearoperator(p)


def relative_residual(op: LinearOperator, x: np.ndarray, y: np.ndarray) -> float:
    """``‖A x − y‖ / ‖y‖`` (0 when ``y`` is zero and ``A x`` is too)."""
    r = float(np.linalg.norm(op.matvec(x.ravel()) - y))
    ny = float(np.linalg.norm(y))
    return r / ny if ny > 0 else r


def data_scale(acquisition: Acquisition) -> float:
    """The mean non-zero eigenvalue of ``AᵀA``, ``‖A‖_F² / min(m, N)``: ``N`` for ±1 Hadamard
    patterns (every measured row has norm² ``N``); for explicit patterns their own value, so that
    ``½‖Ax − y‖²/s`` weighs the data alike for 0/1, ±1 and split patterns."""
    if acquisition.patterns is None:
        return float(acquisition.n_pixels)
    p = np.asarray(acquisition.patterns, dtype=np.float64)
    rank_bound = min(p.shape[0], p.shape[1])
    return float(np.sum(p * p)) / rank_bound if rank_bound else 0.0


#: OMP's tie window: correlation scores within this relative distance of the best count as tied and
#: the lowest atom index wins (:func:`nirspi_pipe.solvers.omp.pick_atom`; the OpenCL kernels use
#: the same constant, so both back ends pick the same atoms).
TIE_RTOL = 1e-9
