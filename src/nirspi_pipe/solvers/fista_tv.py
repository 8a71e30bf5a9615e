"""Solver ``fista_tv``: FISTA on least squares plus total variation (Beck & Teboulle 2009)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.restoration import denoise_tv_chambolle

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.solvers.common import checked_coefficients, measurement_operator, relative_residual
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["FistaTVSolver", "lipschitz"]


def lipschitz(op, n_iter: int = 30, seed: int = 0) -> float:  # type: ignore[no-untyped-def]
    """Largest eigenvalue of ``AᵀA`` by power iteration (``n_iter`` steps), +2 % margin."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(op.shape[1])
    v /= np.linalg.norm(v)
    lam = 0.0
    for _ in range(n_iter):
        w = op.rmatvec(op.matvec(v))
        lam = float(np.linalg.norm(w))
        if lam == 0.0:
            return 0.0
        v = w / lam
    return 1.02 * lam


@dataclass(frozen=True)
class FistaTVSolver:
    """Solver ``fista_tv``: ``argmin_x ½‖A x − y‖²/N + λ·TV(x)``.

    ``A`` is the measurement operator (fast subsampled Hadamard, or explicit patterns), ``y`` the
    calibrated measurements and ``N = n²``; dividing the data term by ``N`` makes it, for a full
    Hadamard acquisition, ``½‖x − x_true‖²``, so ``lam`` is the ROF weight of an image in
    relative radiance (``λ ≈ 0.01–0.1`` for [0, 1] images). FISTA: a gradient step on the data
    term, then the TV proximal step (isotropic TV, Chambolle's projection by scikit-image, warm
    start impossible there, so ``tv_iter`` inner iterations each time), with Nesterov momentum.
    Starts from the zero-filled/adjoint image ``Aᵀy/N``.

    Attributes:
        lam: TV weight λ (relative radiance), ≥ 0; 0 gives plain least squares.
        max_iter: outer FISTA iterations at most.
        tol: stop when ``‖x_k − x_{k−1}‖ ≤ tol · ‖x_k‖``.
        tv_iter: inner iterations of each TV proximal step.
        nonneg: project onto ``x ≥ 0`` after each proximal step (radiance cannot be negative).
    """

    lam: float = 0.02
    max_iter: int = 100
    tol: float = 1e-4
    tv_iter: int = 20
    nonneg: bool = False

    def __post_init__(self) -> None:
        if not (np.isfinite(self.lam) and self.lam >= 0):
            raise ConfigError("lam", self.lam, "a TV weight >= 0")
        if not isinstance(self.max_iter, (int, np.integer)) or self.max_iter < 1:
            raise ConfigError("max_iter", self.max_iter, "an integer >= 1")
        if not (np.isfinite(self.tol) and self.tol >= 0):
            raise ConfigError("tol", self.tol, "a relative tolerance >= 0")
        if not isinstance(self.tv_iter, (int, np.integer)) or self.tv_iter < 1:
            raise ConfigError("tv_iter", self.tv_iter, "an integer >= 1")

    def _prox(self, z: np.ndarray, step: float) -> np.ndarray:
        """``argmin_u ½‖u − z‖² + step·λ·TV(u)`` (scikit-image's weight is that factor)."""
        weight = step * self.lam
        u = z if weight == 0 else denoise_tv_chambolle(z, weight=weight, eps=0.0, max_num_iter=self.tv_iter)
        return np.maximum(u, 0.0) if self.nonneg else u

    def solve(self, acquisition: Acquisition) -> Image2D:
        y = checked_coefficients(acquisition, "fista_tv")
        op = measurement_operator(acquisition)
        n, size = acquisition.n, acquisition.n_pixels
        hadamard = acquisition.patterns is None
        # Lipschitz constant of the gradient of ½‖Ax − y‖²/N: ‖A‖²/N, exactly 1 on the Hadamard
        # path (orthogonal rows of norm² N).
        big_l = 1.0 if hadamard else lipschitz(op) / size
        if big_l == 0.0:
            return Image2D(np.zeros((n, n)), info={"iterations": 0, "stop_reason": "zero_operator"})
        step = 1.0 / big_l

        x = (op.rmatvec(y) / size).reshape(n, n)
        z, t = x.copy(), 1.0
        stop, it = "max_iter", 0
        for it in range(1, self.max_iter + 1):  # noqa: B007 - the count is read after the loop
            grad = (op.rmatvec(op.matvec(z.ravel()) - y) / size).reshape(n, n)
            x_new = self._prox(z - step * grad, step)
            t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            z = x_new + ((t - 1.0) / t_new) * (x_new - x)  # Nesterov momentum (FISTA)
            change = float(np.linalg.norm(x_new - x))
            scale = float(np.linalg.norm(x_new))
            x, t = x_new, t_new
            if change <= self.tol * scale or (scale == 0.0 and change == 0.0):
                stop = "converged"
                break
        info = {
            "iterations": it,
            "stop_reason": stop,
            "relative_residual": relative_residual(op, x, y),
            "lipschitz": big_l,
        }
        return Image2D(x, info=info)
