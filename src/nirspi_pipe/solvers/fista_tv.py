"""Solver ``fista_tv``: FISTA on least squares plus total variation (Beck & Teboulle 2009), with a
weight that follows the noise (SURE, :mod:`nirspi_pipe.solvers.noise`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.solvers.common import (
    checked_coefficients,
    data_scale,
    measurement_operator,
    relative_residual,
)
from nirspi_pipe.solvers.noise import estimate_noise, sure_weight
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["FistaTVSolver", "lipschitz", "choose_weight"]


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


def choose_weight(
    lam: float | str,
    lam_floor: float,
    acquisition: Acquisition,
    y: np.ndarray,
    scale: float,
    solve,  # type: ignore[no-untyped-def]
    forward,  # type: ignore[no-untyped-def]
) -> tuple[float, dict[str, object]]:
    """The TV weight by the documented rule, shared by ``fista_tv`` and the plugin's ``admm_tv``.

    ``lam`` a number: that weight (``rule: fixed``). ``lam: auto``: estimate the noise σ
    (:func:`~nirspi_pipe.solvers.noise.estimate_noise`); σ = 0 (exact data) gives λ = 0, the
    least-squares image, exact at full sampling (``rule: exact``); σ > 0 gives the SURE-optimal λ
    (``rule: sure``). Undersampled (``m < N``), λ is at least ``lam_floor``, the prior that fills
    the unmeasured coefficients (``rule: floor`` when it wins). ``scale`` is the data term's
    normalisation ``s`` (``½‖Ax − y‖²/s``), so the pixel noise is ``σ/√s``.
    """
    if not isinstance(lam, str):
        return float(lam), {"lam": float(lam), "lam_rule": "fixed"}
    noise = estimate_noise(acquisition)
    info: dict[str, object] = {"noise_sigma": float(noise.sigma), "noise_method": noise.method}
    rms = float(np.sqrt(np.mean(y * y))) if y.size else 0.0
    undersampled = len(y) < acquisition.n_pixels
    floor = float(lam_floor) if undersampled else 0.0
    if not noise.sigma > 1e-12 * rms:
        chosen, rule = 0.0, "exact"
    else:
        chosen, extra = sure_weight(solve, forward, y, noise.sigma, noise.sigma / np.sqrt(scale))
        info.update(extra)
        rule = "sure"
    if floor > chosen:
        chosen, rule = floor, "floor"
    info.update(lam=chosen, lam_rule=rule)
    return chosen, info


@dataclass(frozen=True)
class FistaTVSolver:
    """Solver ``fista_tv``: ``argmin_x ½‖A x − y‖²/s + λ·TV(x)``.

    ``A`` is the measurement operator (fast subsampled Hadamard, or explicit patterns), ``y`` the
    calibrated measurements and ``s`` the mean non-zero eigenvalue of ``AᵀA``,
    ``‖A‖_F²/min(m, N)`` (``= N`` for ±1 Hadamard patterns, so a full acquisition's data term is
    ``½‖x − x_true‖²``); ``λ`` is then the ROF weight of an image in relative radiance whatever the
    patterns (0/1, ±1, split). FISTA: a gradient step on the data term, then the TV proximal step
    (isotropic TV, Chambolle's projection by scikit-image, ``tv_iter`` inner iterations), with
    Nesterov momentum. Starts from ``Aᵀy/s``.

    ``lam: auto`` (default) sets λ from the data's own noise by SURE (:func:`choose_weight`);
    λ = 0 with explicit patterns is solved by LSQR to its tolerance (solver ``lstsq``).

    Attributes:
        lam: TV weight λ (relative radiance) ≥ 0, or ``auto``.
        lam_floor: smallest λ under ``auto`` when undersampled (relative radiance): the weight of
            the TV prior on the unmeasured coefficients, measured in docs/reconstruction.md
            (issue #4's fixed default, 44.6–45.3 dB on the sphere at 25 %).
        max_iter: outer FISTA iterations at most.
        tol: stop when ``‖x_k − x_{k−1}‖ ≤ tol · ‖x_k‖``.
        tv_iter: inner iterations of each TV proximal step.
        nonneg: project onto ``x ≥ 0`` after each proximal step (radiance cannot be negative).
    """

    lam: float | str = "auto"
    lam_floor: float = 0.02
    max_iter: int = 100
    tol: float = 1e-4
    tv_iter: int = 20
    nonneg: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.lam, str):
            if self.lam != "auto":
                raise ConfigError("lam", self.lam, "auto, or a TV weight >= 0")
        elif not (np.isfinite(self.lam) and self.lam >= 0):
            raise ConfigError("lam", self.lam, "auto, or a TV weight >= 0")
        if not (np.isfinite(self.lam_floor) and self.lam_floor >= 0):
            raise ConfigError("lam_floor", self.lam_floor, "a TV weight >= 0")
        if not isinstance(self.max_iter, (int, np.integer)) or self.max_iter < 1:
            raise ConfigError("max_iter", self.max_iter, "an integer >= 1")
        if not (np.isfinite(self.tol) and self.tol >= 0):
            raise ConfigError("tol", self.tol, "a relative tolerance >= 0")
        if not isinstance(self.tv_iter, (int, np.integer)) or self.tv_iter < 1:
            raise ConfigError("tv_iter", self.tv_iter, "an integer >= 1")

    def _prox(self, z: np.ndarray, weight: float) -> np.ndarray:
        """``argmin_u ½‖u − z‖² + weight·TV(u)`` (scikit-image's weight is that factor)."""
        # imported here: skimage.restoration pulls in scipy.stats (1.0-1.3 s, python -X importtime),
        # which every nirspi-run with the example plugin installed paid twice at start-up
        from skimage.restoration import denoise_tv_chambolle

        u = z if weight == 0 else denoise_tv_chambolle(z, weight=weight, eps=0.0, max_num_iter=self.tv_iter)
        return np.maximum(u, 0.0) if self.nonneg else u

    def _fista(self, op, y: np.ndarray, n: int, scale: float, big_l: float, lam: float):  # type: ignore[no-untyped-def]
        step = 1.0 / big_l
        x = (op.rmatvec(y) / scale).reshape(n, n)
        z, t = x.copy(), 1.0
        stop, it = "max_iter", 0
        for it in range(1, self.max_iter + 1):  # noqa: B007 - the last count is returned as iterations
            grad = (op.rmatvec(op.matvec(z.ravel()) - y) / scale).reshape(n, n)
            x_new = self._prox(z - step * grad, step * lam)
            t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            z = x_new + ((t - 1.0) / t_new) * (x_new - x)  # Nesterov momentum (FISTA)
            change = float(np.linalg.norm(x_new - x))
            norm = float(np.linalg.norm(x_new))
            x, t = x_new, t_new
            if change <= self.tol * norm or (norm == 0.0 and change == 0.0):
                stop = "converged"
                break
        return x, it, stop

    def solve(self, acquisition: Acquisition) -> Image2D:
        y = checked_coefficients(acquisition, "fista_tv")
        op = measurement_operator(acquisition)
        n = acquisition.n
        hadamard = acquisition.patterns is None
        scale = data_scale(acquisition)
        # Lipschitz constant of the gradient of ½‖Ax − y‖²/s: ‖A‖²/s, exactly 1 on the Hadamard
        # path (orthogonal rows of norm² N).
        big_l = 1.0 if hadamard else (lipschitz(op) / scale if scale > 0 else 0.0)
        if big_l == 0.0:
            return Image2D(np.zeros((n, n)), info={"iterations": 0, "stop_reason": "zero_operator"})

        def solve_for(data: np.ndarray, lam: float) -> np.ndarray:
            return self._fista(op, data, n, scale, big_l, lam)[0]

        lam, weight_info = choose_weight(self.lam, self.lam_floor, acquisition, y, scale, solve_for, op.matvec)
        if lam == 0.0 and not hadamard:
            from nirspi_pipe.solvers.lstsq import LstsqSolver

            ls = LstsqSolver().solve(acquisition)
            return Image2D(ls.data, info={**ls.info, **weight_info, "lipschitz": big_l})
        x, it, stop = self._fista(op, y, n, scale, big_l, lam)
        info = {
            "iterations": it,
            "stop_reason": stop,
            "relative_residual": relative_residual(op, x, y),
            "lipschitz": big_l,
            **weight_info,
        }
        return Image2D(x, info=info)
