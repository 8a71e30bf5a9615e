"""ADMM total-variation reconstruction of undersampled Hadamard acquisitions.

Problem (relative radiance ``x``, ``n × n``)::

    minimise  ½ ‖A x − c‖²  +  λ ‖D x‖₁     (subject to x ≥ 0 when ``nonneg``)

where ``A = S H / √N`` keeps the measured rows of the orthonormal 2D Hadamard transform
(``H`` Sylvester, ``N = n²``, ``S`` the row selection given by ``acquisition.indices``),
``c = coefficients / √N`` and ``D`` the forward-difference gradient with Neumann boundaries
(anisotropic TV). Splitting ``w = x`` (data), ``v = D x`` (gradient) and ``p = x`` (positivity)
gives an ADMM whose every step is closed-form and ``O(N log N)``:

* ``x``: ``(q I + DᵀD) x = …`` is diagonal in the DCT-II basis (Neumann Laplacian);
* ``w``: ``(AᵀA + ρ I) w = Aᵀc + ρ b`` is diagonal in the Hadamard basis (A has orthonormal
  rows), solved with two fast Walsh–Hadamard transforms; with explicit patterns ``P`` (any
  ``(m, N)`` matrix: 0/1, ±1, split) ``A = P/√s`` with ``s = ‖P‖_F²/min(m, N)`` (the same data
  weight as ``fista_tv``), and the system is solved by conjugate gradients, warm-started;
* ``v``: soft thresholding; ``p``: projection onto ``x ≥ 0``.

This is the augmented-Lagrangian/alternating scheme of TVAL3 (Li, Yin & Zhang 2013) with exact
sub-problem solutions instead of TVAL3's one-step gradient updates.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.fft import dctn, idctn
from scipy.sparse.linalg import LinearOperator, cg

from nirspi_pipe.patterns.hadamard import fwht
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.solvers.common import data_scale, measurement_operator
from nirspi_pipe.solvers.fista_tv import choose_weight
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["ADMMTVSolver", "admm_tv"]


def _grad(x: np.ndarray) -> np.ndarray:
    """Forward differences ``(2, n, n)`` with Neumann boundaries (zero across the last edge)."""
    g = np.zeros((2, *x.shape))
    g[0, :-1, :] = x[1:, :] - x[:-1, :]
    g[1, :, :-1] = x[:, 1:] - x[:, :-1]
    return g


def _grad_adjoint(g: np.ndarray) -> np.ndarray:
    """``Dᵀ g`` (minus the divergence) for :func:`_grad`."""
    out = np.zeros(g.shape[1:])
    out[:-1, :] -= g[0, :-1, :]
    out[1:, :] += g[0, :-1, :]
    out[:, :-1] -= g[1, :, :-1]
    out[:, 1:] += g[1, :, :-1]
    return out


def _laplacian_eigenvalues(n: int) -> np.ndarray:
    """Eigenvalues of ``DᵀD`` in the orthonormal DCT-II basis, ``(n, n)``."""
    lam = 2.0 - 2.0 * np.cos(np.pi * np.arange(n) / n)
    return lam[:, None] + lam[None, :]


def admm_tv(
    n: int,
    indices: np.ndarray,
    coefficients: np.ndarray,
    tv_weight: float = 0.02,
    rho: float = 1.0,
    max_iter: int = 300,
    tol: float = 1e-4,
    nonneg: bool = True,
    patterns: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, object]]:
    """Reconstruct an ``n × n`` image from 2D Hadamard coefficients by ADMM-TV.

    Args:
        n: image side (power of two).
        indices: ``(m,)`` flat pattern indices (``k = i·n + j``); repeats are averaged.
        coefficients: ``(m,)`` measured ``Σ P_k ⊙ x`` (relative radiance × pixels).
        tv_weight: λ, weight of the anisotropic TV term (relative radiance per pixel).
        rho: ADMM penalty parameter (dimensionless).
        max_iter: iteration cap.
        tol: relative primal/dual residual at which to stop.
        nonneg: constrain the image to ``x ≥ 0``.
        patterns: ``(m, n²)`` explicit patterns (row-major pixels) measured as ``coefficients``;
            None for Hadamard ``indices``.

    Returns:
        The image (relative radiance) and bookkeeping (iterations, stop reason, residuals).
    """
    big_n = n * n
    root = np.sqrt(big_n)
    if patterns is None:
        idx = np.asarray(indices, dtype=np.int64)
        counts = np.bincount(idx, minlength=big_n).astype(np.float64)
        sums = np.bincount(idx, weights=np.asarray(coefficients, dtype=np.float64) / root, minlength=big_n)
        measured = counts > 0

        def t(x_flat: np.ndarray) -> np.ndarray:  # orthonormal Hadamard transform (self-inverse)
            return fwht(x_flat) / root

        # Initial guess: zero-filled inverse of the averaged coefficients.
        c_hat = np.where(measured, sums / np.maximum(counts, 1.0), 0.0)
        x = t(c_hat).reshape(n, n)

        def w_step(b: np.ndarray, w_prev: np.ndarray) -> np.ndarray:
            # (AᵀA + ρI) w = Aᵀc + ρ b, diagonal in the Hadamard domain.
            return t((sums + rho * t(b.ravel())) / (counts + rho)).reshape(n, n)
    else:
        p = np.asarray(patterns, dtype=np.float64)
        scale = float(np.sum(p * p)) / max(1, min(p.shape))
        p_s = p / np.sqrt(scale)
        aty = p_s.T @ (np.asarray(coefficients, dtype=np.float64) / np.sqrt(scale))
        normal = LinearOperator((big_n, big_n), matvec=lambda v: p_s.T @ (p_s @ v) + rho * v, dtype=np.float64)
        x = aty.reshape(n, n)

        def w_step(b: np.ndarray, w_prev: np.ndarray) -> np.ndarray:
            sol, _ = cg(normal, aty + rho * b.ravel(), x0=w_prev.ravel(), rtol=1e-6, maxiter=200)
            return sol.reshape(n, n)

    q = 2.0 if nonneg else 1.0
    denom = q + _laplacian_eigenvalues(n)
    w, v, p = x.copy(), _grad(x), np.maximum(x, 0.0)
    uw, uv, up = np.zeros_like(x), np.zeros_like(v), np.zeros_like(x)
    thresh = tv_weight / rho
    stop, it, r_norm, s_norm = "max_iter", 0, np.inf, np.inf
    for it in range(1, max_iter + 1):
        rhs = (w - uw) + _grad_adjoint(v - uv)
        if nonneg:
            rhs = rhs + (p - up)
        x = idctn(dctn(rhs, type=2, norm="ortho") / denom, type=2, norm="ortho")
        w_old, v_old, p_old = w, v, p
        w = w_step(x + uw, w)
        gx = _grad(x)
        z = gx + uv
        v = np.sign(z) * np.maximum(np.abs(z) - thresh, 0.0)
        if nonneg:
            p = np.maximum(x + up, 0.0)
            up = up + x - p
        uw = uw + x - w
        uv = uv + gx - v
        r_norm = float(
            np.sqrt(np.sum((x - w) ** 2) + np.sum((gx - v) ** 2) + (np.sum((x - p) ** 2) if nonneg else 0.0))
        )
        s_norm = rho * float(
            np.sqrt(np.sum((w - w_old) ** 2) + np.sum((v - v_old) ** 2) + (np.sum((p - p_old) ** 2) if nonneg else 0.0))
        )
        scale = max(float(np.linalg.norm(x)), 1e-12)
        if it > 1 and r_norm <= tol * scale and s_norm <= tol * scale:
            stop = "converged"
            break
    image = np.maximum(x, 0.0) if nonneg else x
    return image, {
        "iterations": it,
        "stop_reason": stop,
        "primal_residual": r_norm,
        "dual_residual": s_norm,
    }


@dataclass(frozen=True)
class ADMMTVSolver:
    """Solver ``admm_tv`` (plugin nirspi-admm): total-variation-regularised reconstruction by ADMM
    of a Hadamard acquisition or of explicit patterns. See :func:`admm_tv` for the parameters.

    ``tv_weight: auto`` (default) sets λ from the data's own noise, by the rule of
    :func:`nirspi_pipe.solvers.fista_tv.choose_weight` (noise from the split pairs, SURE-optimal
    weight, 0 for exact data at full sampling, at least ``lam_floor`` when undersampled).
    """

    tv_weight: Annotated[float | str, Range(0.0, None, "a weight", also=("auto",))] = "auto"
    lam_floor: Annotated[float, Range(0.0, None, "a weight")] = 0.02
    rho: Annotated[float, Range(0.0, None, "a penalty", lo_open=True)] = 1.0
    max_iter: Annotated[int, Range(1, None, "an integer", integer=True)] = 300
    tol: Annotated[float, Range(0.0, 1.0, "a relative tolerance", lo_open=True, hi_open=True)] = 1e-4
    nonneg: bool = True

    def __post_init__(self) -> None:
        check_ranges(self)

    def solve(self, acquisition: Acquisition) -> Image2D:
        """Reconstruct relative radiance from ``acquisition.coefficients()``."""
        coeffs = acquisition.coefficients()
        if not np.all(np.isfinite(coeffs)):
            warnings.warn("admm_tv: non-finite measurements were dropped", stacklevel=2)
        keep = np.isfinite(coeffs)
        patterns = None if acquisition.patterns is None else np.asarray(acquisition.patterns)[keep]
        indices = acquisition.indices[keep]

        def solve_for(data: np.ndarray, lam: float) -> np.ndarray:
            return admm_tv(
                acquisition.n,
                indices,
                data,
                tv_weight=lam,
                rho=float(self.rho),
                max_iter=int(self.max_iter),
                tol=float(self.tol),
                nonneg=bool(self.nonneg),
                patterns=patterns,
            )

        y = coeffs[keep]
        op = measurement_operator(acquisition) if keep.all() else None
        forward = op.matvec if op is not None else (lambda v: measurement_operator(acquisition).matvec(v)[keep])
        lam, weight_info = choose_weight(
            self.tv_weight,
            self.lam_floor,
            acquisition,
            y,
            data_scale(acquisition),
            lambda d, w: solve_for(d, w)[0],
            forward,
        )
        if lam == 0.0 and patterns is not None:  # exact data, explicit patterns: least squares to tolerance
            from nirspi_pipe.solvers.lstsq import LstsqSolver

            ls = LstsqSolver().solve(acquisition)
            return Image2D(ls.data, info={**ls.info, **weight_info})
        image, info = solve_for(y, lam)
        return Image2D(image, info={**info, **weight_info})
