"""Solver ``fista_tv``: monotone FISTA on least squares plus total variation (Beck & Teboulle 2009), with a
weight chosen from the data: SURE at full sampling (:mod:`nirspi_pipe.solvers.noise`), hold-out
cross-validation when undersampled (:mod:`nirspi_pipe.solvers.crossval`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from nirspi_pipe.patterns.hadamard import fwht
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.solvers.common import (
    checked_coefficients,
    data_scale,
    measurement_operator,
    relative_residual,
)
from nirspi_pipe.solvers.crossval import MIN_MEASUREMENTS, cv_iterations, cv_weight, weight_grid
from nirspi_pipe.solvers.lstsq import LstsqSolver
from nirspi_pipe.solvers.noise import estimate_noise, sure_weight
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["FistaTVSolver", "lipschitz", "choose_weight", "tv_prox"]

#: Up to this many pixels (16²) the Hadamard rows are applied as a dense ``(m, N)`` product (at 8²
#: the fast transform's per-call overhead is most of a FISTA iteration; ``nirspi-bench fista --auto``).
DENSE_MAX_PIXELS = 256
#: Up to this many pixels (8²) the TV prox's differences are one product with a ``(2N, N)`` matrix:
#: 148 against 181 µs per 5-iteration prox at 8², but 677 against 214 µs at 16² (timeit, loaded machine).
DENSE_PROX_MAX_PIXELS = 64
#: Chambolle's step (scikit-image's ``1/(2·ndim)``).
_TAU = 0.25


def tv_prox(v: np.ndarray, weight: np.ndarray, p: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """``argmin_u ½‖u − v‖² + weight·TV(u)`` for a batch ``v`` ``(B, n, n)``, isotropic TV.

    Chambolle's (2004) projection algorithm, step for step scikit-image's
    ``denoise_tv_chambolle(v, weight, eps=0, max_num_iter=iters)`` (tested equal), with the dual
    ``p`` ``(B, 2, n, n)`` passed in and returned, so that FISTA warm-starts each prox from the
    previous one's dual. ``weight`` ``(B, 1, 1)``; 0 gives ``v``. Up to ``DENSE_PROX_MAX_PIXELS``
    pixels the differences are products with a small matrix (fewer numpy calls).
    """
    w = np.minimum(_TAU / np.maximum(weight, 1e-300), 1e30)
    n = v.shape[-1]
    if n * n <= DENSE_PROX_MAX_PIXELS:
        return _tv_prox_dense(v, w, p, iters)
    g = np.zeros_like(p)
    out = v
    for _ in range(iters):
        d = -p[:, 0] - p[:, 1]
        d[:, 1:, :] += p[:, 0, :-1, :]
        d[:, :, 1:] += p[:, 1, :, :-1]
        out = v + d
        g[:, 0, :-1, :] = out[:, 1:, :] - out[:, :-1, :]
        g[:, 1, :, :-1] = out[:, :, 1:] - out[:, :, :-1]
        norm = np.sqrt(g[:, 0] ** 2 + g[:, 1] ** 2)
        norm *= w
        norm += 1.0
        p = (p - _TAU * g) / norm[:, None]
    return out, p


def total_variation(v: np.ndarray) -> np.ndarray:
    """Isotropic TV of each image of a batch ``(B, n, n)``: the sum over pixels of the norm of the
    forward differences (0 past the last row/column), the TV whose prox :func:`tv_prox` is."""
    gr = np.zeros_like(v)
    gc = np.zeros_like(v)
    gr[:, :-1, :] = v[:, 1:, :] - v[:, :-1, :]
    gc[:, :, :-1] = v[:, :, 1:] - v[:, :, :-1]
    return np.sum(np.sqrt(gr * gr + gc * gc), axis=(1, 2))


@functools.lru_cache(maxsize=8)
def _difference_matrix(n: int) -> np.ndarray:
    """``D`` ``(2N, N)``: forward differences along rows then columns, 0 on the last row/column
    (the gradient of :func:`tv_prox`); ``out = v + p D`` and ``g = out Dᵀ`` on flat batches."""
    eye = np.eye(n * n).reshape(n * n, n, n)
    g = np.zeros((n * n, 2, n, n))
    g[:, 0, :-1, :] = eye[:, 1:, :] - eye[:, :-1, :]
    g[:, 1, :, :-1] = eye[:, :, 1:] - eye[:, :, :-1]
    return np.ascontiguousarray(g.reshape(n * n, 2 * n * n).T)


def _tv_prox_dense(v: np.ndarray, w: np.ndarray, p: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray]:
    batch, n = v.shape[0], v.shape[-1]
    size = n * n
    dm = _difference_matrix(n)
    flat_v = v.reshape(batch, size)
    pf = p.reshape(batch, 2 * size)
    wf = w.reshape(batch, 1)
    out = flat_v
    for _ in range(iters):
        out = flat_v + pf @ dm
        g = out @ dm.T
        sq = g * g
        norm = np.sqrt(sq[:, :size] + sq[:, size:])
        norm *= wf
        norm += 1.0
        pf = ((pf - _TAU * g).reshape(batch, 2, size) / norm[:, None, :]).reshape(batch, 2 * size)
    return out.reshape(batch, n, n), pf.reshape(batch, 2, n, n)


def lipschitz(op, n_iter: int = 30, seed: int = 0) -> float:
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
    solve,
    forward,
    fit=None,
    predict=None,
    max_iter: int = 100,
) -> tuple[float, dict[str, object]]:
    """The TV weight by the documented rule, shared by ``fista_tv`` and the plugin's ``admm_tv``.

    ``lam`` a number: that weight (``rule: fixed``). ``lam: auto``: estimate the noise σ
    (:func:`~nirspi_pipe.solvers.noise.estimate_noise`), then

    * full sampling (``m ≥ N``): σ = 0 (exact data) gives λ = 0, the least-squares image, exact
      (``rule: exact``); σ > 0 the SURE-optimal λ (``rule: sure``);
    * undersampled, with ``fit``/``predict`` given (``fista_tv``) and at least
      ``MIN_MEASUREMENTS``: hold-out cross-validation over a grid
      (:func:`~nirspi_pipe.solvers.crossval.cv_weight`, ``rule: cv``), noisy or not; the record
      has the chosen weight's fit on the training set (``cv_fit``, not recorded) for a warm start;
    * undersampled otherwise (``admm_tv``, or too few measurements): SURE (σ > 0) or 0, at least
      ``lam_floor`` (``rule: floor`` when the floor wins).

    ``scale`` is the data term's normalisation ``s`` (``½‖Ax − y‖²/s``), so the pixel noise is
    ``σ/√s``; ``max_iter`` is one solve's iterations, which sets the training fits' budget
    (:func:`~nirspi_pipe.solvers.crossval.cv_iterations`).
    """
    if not isinstance(lam, str):
        return float(lam), {"lam": float(lam), "lam_rule": "fixed"}
    noise = estimate_noise(acquisition)
    info: dict[str, object] = {"noise_sigma": float(noise.sigma), "noise_method": noise.method}
    rms = float(np.sqrt(np.mean(y * y))) if y.size else 0.0
    undersampled = len(y) < acquisition.n_pixels
    exact = not noise.sigma > 1e-12 * rms
    sigma = 0.0 if exact else float(noise.sigma)
    if undersampled and fit is not None and predict is not None and len(y) >= MIN_MEASUREMENTS:
        # image rms level: ‖Aᵀy/s‖/√N; pixel noise σ/√s
        x_rms = rms * np.sqrt(len(y)) / np.sqrt(scale * acquisition.n_pixels) if scale > 0 else 0.0
        grid = weight_grid(x_rms, sigma / np.sqrt(scale) if scale > 0 else 0.0)
        its = cv_iterations(grid, sigma > 0, max_iter)
        chosen, start, extra = cv_weight(fit, predict, y, acquisition.n_pixels, sigma, grid, its)
        info.update(extra)
        info.update(lam=chosen, lam_rule="cv", cv_fit=start)
        return chosen, info
    floor = float(lam_floor) if undersampled else 0.0
    if exact:
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
    patterns (0/1, ±1, split). Monotone FISTA (MFISTA, Beck & Teboulle 2009b): a gradient step on
    the data term, then the TV proximal step (isotropic TV, Chambolle's projection, :func:`tv_prox`,
    ``tv_iter`` inner iterations from the previous step's dual), with Nesterov momentum; a step that
    would raise the objective is not taken (the momentum still uses it). Plain FISTA with this
    inexact, warm-started prox diverged at large λ (``tests/test_crossval.py``). Starts from
    ``Aᵀy/s``.

    ``lam: auto`` (default) sets λ from the data (:func:`choose_weight`): SURE at full sampling,
    hold-out cross-validation undersampled; λ = 0 with explicit patterns is solved by LSQR to its
    tolerance (solver ``lstsq``).

    Attributes:
        lam: TV weight λ (relative radiance) ≥ 0, or ``auto``.
        lam_floor: smallest λ under ``auto`` when undersampled but with fewer than
            ``crossval.MIN_MEASUREMENTS`` measurements, too few to hold any out (relative
            radiance; issue #4's fixed default, 44.6–45.3 dB on the sphere at 25 %).
        max_iter: outer FISTA iterations at most.
        tol: stop when ``‖x_k − x_{k−1}‖ ≤ tol · ‖x_k‖``.
        tv_iter: inner iterations of each TV proximal step, started from the previous step's dual
            (docs/reconstruction.md: 5 warm against the former 20 cold).
        nonneg: project onto ``x ≥ 0`` after each proximal step (radiance cannot be negative).
    """

    lam: Annotated[float | str, Range(0.0, None, "a TV weight", also=("auto",))] = "auto"
    lam_floor: Annotated[float, Range(0.0, None, "a TV weight")] = 0.02
    max_iter: Annotated[int, Range(1, None, "an integer", integer=True)] = 100
    tol: Annotated[float, Range(0.0, None, "a relative tolerance")] = 1e-4
    tv_iter: Annotated[int, Range(1, None, "an integer", integer=True)] = 5
    nonneg: bool = False

    def __post_init__(self) -> None:
        check_ranges(self)

    def _fista(
        self,
        fwd,
        adj,
        y: np.ndarray,
        n: int,
        scale: float,
        big_l: float,
        lam: np.ndarray,
        x0: np.ndarray | None = None,
        max_iter: int | None = None,
        tv_iter: int | None = None,
    ) -> tuple[np.ndarray, int, str]:
        """FISTA for a batch of weights ``lam`` ``(B,)`` on measurements ``y`` ``(B, m)``;
        ``fwd``/``adj`` map ``(B, N) ↔ (B, m)``. Returns ``(B, n, n)``, iterations, stop reason
        (``converged`` when every member has)."""
        batch = lam.size
        step = 1.0 / big_l
        x = (adj(y) / scale).reshape(batch, n, n) if x0 is None else np.array(x0, dtype=np.float64)
        z, t = x.copy(), 1.0
        weight = (step * lam)[:, None, None]
        p = np.zeros((batch, 2, n, n))
        stop, it = "max_iter", 0
        inner = self.tv_iter if tv_iter is None else tv_iter
        live = lam > 0
        prox_all, prox_any = bool(live.all()), bool(live.any())

        def objective(v: np.ndarray) -> np.ndarray:
            r = fwd(v.reshape(batch, -1)) - y
            return 0.5 * np.sum(r * r, axis=1) / scale + lam * total_variation(v)

        f_x = objective(x)
        for it in range(1, (self.max_iter if max_iter is None else max_iter) + 1):  # noqa: B007 - returned
            grad = (adj(fwd(z.reshape(batch, -1)) - y) / scale).reshape(batch, n, n)
            u = z - step * grad
            if prox_all:
                u, p = tv_prox(u, weight, p, inner)
            elif prox_any:  # λ = 0 members: the prox is the identity, skip its cost
                u[live], p[live] = tv_prox(u[live], weight[live], p[live], inner)
            if self.nonneg:
                u = np.maximum(u, 0.0)
            # MFISTA (Beck & Teboulle 2009b): keep the better of the step u and x, so the objective
            # never rises; with a warm-started inexact prox, plain FISTA diverged at large λ
            # (tests/test_crossval.py::test_fista_tv_decreases_its_objective_at_large_weights)
            f_u = objective(u)
            better = f_u <= f_x
            x_new = np.where(better[:, None, None], u, x)
            t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            z = x_new + (t / t_new) * (u - x_new) + ((t - 1.0) / t_new) * (x_new - x)
            change = np.sqrt(np.sum((u - x) ** 2, axis=(1, 2)))
            norm = np.sqrt(np.sum(x_new**2, axis=(1, 2)))
            x, t, f_x = x_new, t_new, np.where(better, f_u, f_x)
            if np.all(change <= self.tol * norm):
                stop = "converged"
                break
        return x, it, stop

    def solve(self, acquisition: Acquisition, start=None) -> Image2D:
        """The TV image of ``acquisition``.

        ``start``: ``rows ↦ (n, n)``, the image from which FISTA starts when fitting the
        measurements at positions ``rows`` (``None``: all of them), for the cross-validation's
        training fits and the final fit alike (``completion``'s ``refine: tv`` passes its own
        estimate); ``None`` (default) starts from ``Aᵀy/s`` (the training fits) and from the chosen
        weight's training fit (the final fit).
        """
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
        fwd, adj = _batch_operator(acquisition)

        def fit(rows: np.ndarray, data: np.ndarray, lams: np.ndarray, iterations: int) -> np.ndarray:
            f, a = _batch_operator(acquisition, rows)
            x0 = None if start is None else np.broadcast_to(start(rows), (lams.size, n, n))
            return self._fista(f, a, data, n, scale, big_l, lams, x0=x0, max_iter=iterations)[0]

        def predict(images: np.ndarray, rows: np.ndarray) -> np.ndarray:
            return _batch_operator(acquisition, rows)[0](images.reshape(images.shape[0], -1))

        def solve_for(data: np.ndarray, lam: float) -> np.ndarray:
            return self._fista(fwd, adj, data[None, :], n, scale, big_l, np.array([lam]))[0][0]

        lam, weight_info = choose_weight(
            self.lam, self.lam_floor, acquisition, y, scale, solve_for, op.matvec, fit, predict, self.max_iter
        )
        x0 = weight_info.pop("cv_fit", None)
        if start is not None:
            x0 = start(None)
        if lam == 0.0 and not hadamard:
            ls = LstsqSolver().solve(acquisition)
            return Image2D(ls.data, info={**ls.info, **weight_info, "lipschitz": big_l})
        start = None if x0 is None else np.asarray(x0)[None]
        xb, it, stop = self._fista(fwd, adj, y[None, :], n, scale, big_l, np.array([lam]), start)
        x = xb[0]
        info = {
            "iterations": it,
            "stop_reason": stop,
            "relative_residual": relative_residual(op, x, y),
            "lipschitz": big_l,
            **weight_info,
        }
        return Image2D(x, info=info)


def _batch_operator(acquisition: Acquisition, rows: np.ndarray | None = None):
    """``(fwd, adj)`` of the acquisition's measurements (those at positions ``rows``, default all)
    on batches: ``fwd`` ``(B, N) → (B, m)``, ``adj`` ``(B, m) → (B, N)``; the fast transform on
    the Hadamard path (``O(B·N log N)``), products with the pattern matrix otherwise."""
    size = acquisition.n_pixels
    if acquisition.patterns is None:
        idx = np.asarray(acquisition.indices, dtype=np.int64)
        if rows is not None:
            idx = idx[rows]
        if size <= DENSE_MAX_PIXELS:  # tiny images: one product beats the transform's reshapes
            rows_h = fwht(np.eye(size)[idx], axis=-1)  # (m, N): the measured rows of H_N
            return (lambda x: x @ rows_h.T), (lambda r: r @ rows_h)

        def fwd(x: np.ndarray) -> np.ndarray:
            return fwht(x, axis=-1)[:, idx]

        def adj(r: np.ndarray) -> np.ndarray:
            full = np.zeros((r.shape[0], size))
            full[:, idx] = r
            return fwht(full, axis=-1)

        return fwd, adj
    pat = np.asarray(acquisition.patterns, dtype=np.float64)
    if rows is not None:
        pat = pat[rows]
    return (lambda x: x @ pat.T), (lambda r: r @ pat)
