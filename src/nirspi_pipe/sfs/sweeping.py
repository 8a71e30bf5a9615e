"""Fast-sweeping solvers for the static Hamilton–Jacobi equations of shape from shading (numpy).

Two schemes, both Gauss–Seidel with the four alternating orderings of fast sweeping:

* ``lax_friedrichs`` — Kao, Osher & Qian (2004), *Lax–Friedrichs sweeping scheme for static
  Hamilton–Jacobi equations*, J. Comput. Phys. 196:367–391. For ``H(x, ∇z) = rhs(x, z)`` the
  cell update is (KOQ Eq. 2.6 with the LF numerical Hamiltonian)::

      z_ij ← [ rhs − H(p_c, q_c) + σx (z_E + z_W)/(2hx) + σy (z_N + z_S)/(2hy) ] / (σx/hx + σy/hy)

  with centred differences ``p_c = (z_E − z_W)/(2hx)``, ``q_c = (z_S − z_N)/(2hy)`` and artificial
  viscosities ``σx ≥ max|∂H/∂p|``, ``σy ≥ max|∂H/∂q|``. Only interior cells are updated; after
  every sweep the four grid edges get KOQ's extrapolation rule
  ``Z₁ = min(max(2Z₂ − Z₃, Z₃), Z₁)`` (the rule the paper's Alg. A2 lines 7–10 garble).
* ``godunov`` — the Godunov upwind update of Zhao (2005), *A fast sweeping method for eikonal
  equations*, Math. Comp. 74:603, for ``|∇z| = F`` only. It converges in a handful of sweeps.
* ``second_order`` — second-order upwind sweeping for ``|∇z| = F`` (fast marching's order-2
  differences, with slopes averaged along the upwind edges); see
  :mod:`nirspi_pipe.sfs.second_order`.

Both start from a supersolution (a large value everywhere except the Dirichlet cells) and keep
``z ← min(z, z̄)``, so the iterates decrease monotonically to the viscosity solution.

Vectorisation: in a sweep ordered ``(i↑, j↑)`` a cell needs the *new* values of its upper and
left neighbours and the *old* values of the others, so all cells on one anti-diagonal
``i + j = d`` are independent and are updated together (Detrixhe, Gibou & Min 2013). The
orderings ``(i↓, j↑)`` and ``(i↑, j↓)`` use the diagonals ``i − j = d``. Every scheme here is
symmetric in its neighbours, so the four orderings only change the diagonal sequence.

Grid spacing is one pixel in both directions (``hx = hy = 1``): depths are in pixel units.

Models (``model``):

0. eikonal ``|∇z| = rhs`` (orthographic SFS, light at the viewer);
1. perspective ``sqrt(|∇w|² + (x̂·∇w + 1)²) = rhs`` with ``w = f ln z`` (Prados–Faugeras, light
   at the optical centre, no fall-off);
2. perspective with ``1/r²`` fall-off, ``sqrt(|∇w|² + (x̂·∇w + 1)²) = rhs · exp(−2w/f)``; the
   right side depends on ``w`` and the LF update is solved for it by Newton's method.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from nirspi_pipe.sfs.grid import BIG, SweepProblem, SweepResult, sweep_orders
from nirspi_pipe.sfs.second_order import solve_second_order_numpy

__all__ = ["SweepProblem", "SweepResult", "solve_numpy", "BIG", "SCHEMES", "sweep_orders"]

SCHEMES = ("lax_friedrichs", "godunov", "second_order")


def _subset(order: np.ndarray, starts: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Restrict a diagonal ordering to the cells where ``keep`` (flat bool) is True."""
    sel = keep[order]
    counts = np.add.reduceat(sel.astype(np.int64), starts[:-1]) if len(order) else np.zeros(0, np.int64)
    new_starts = np.r_[0, np.cumsum(counts)]
    new_starts = new_starts[np.r_[True, counts > 0]]  # drop empty diagonals
    return order[sel], new_starts


def _hamiltonian(model: int, p: np.ndarray, q: np.ndarray, xh: np.ndarray | None, yh: np.ndarray | None) -> np.ndarray:
    if model == 0:
        return np.sqrt(p * p + q * q)
    t = xh * p + yh * q + 1.0
    return np.sqrt(p * p + q * q + t * t)


def solve_numpy(
    problem: SweepProblem,
    scheme: str = "lax_friedrichs",
    tol: float = 1e-4,
    max_sweeps: int = 2000,
    slope_average: str = "cos2",
) -> SweepResult:
    """Solve ``problem`` by fast sweeping with vectorised anti-diagonals.

    Args:
        problem: the grid problem.
        scheme: ``lax_friedrichs`` (any model), ``godunov`` or ``second_order`` (model 0 only).
        tol: stop when a full round of four sweeps changes no cell by more than ``tol`` (pixel
            units; KOQ's ``‖z^{k+1} − z^k‖∞ ≤ δ`` over one round).
        max_sweeps: upper bound on single-direction sweeps (rounded up to a multiple of four).
        slope_average: ``second_order`` only: ``cos2`` or ``node`` (see
            :mod:`nirspi_pipe.sfs.second_order`).

    Returns:
        :class:`SweepResult`; ``z`` is finite.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme {scheme!r} not in {SCHEMES}")
    if scheme == "second_order":
        return solve_second_order_numpy(problem, tol, max_sweeps, slope_average)
    if scheme == "godunov" and problem.model != 0:
        raise ValueError("the Godunov update is implemented for the eikonal (model 0) only")
    lf = scheme == "lax_friedrichs"
    zp, rhs, k = _padded(problem)
    z = zp.ravel()
    pc = zp.shape[1]
    plans = _plans(problem, lf, pc)
    fixed_pad = np.zeros(zp.shape, dtype=bool)
    fixed_pad[1:-1, 1:-1] = problem.fixed

    sweeps, round_change, converged = 0, np.inf, False
    max_rounds = max(1, -(-int(max_sweeps) // 4))
    for _ in range(max_rounds):
        round_change = 0.0
        for idx, starts in plans:
            change = _sweep(z, idx, starts, pc, rhs, k if lf else None)
            if lf:
                change = max(change, _koq_boundary(zp, fixed_pad))
            sweeps += 1
            round_change = max(round_change, change)
        if round_change <= tol:
            converged = True
            break
    out = zp[1:-1, 1:-1].copy()
    return SweepResult(out, sweeps, float(round_change), converged)


class _LfCoefficients(NamedTuple):
    """What the Lax-Friedrichs update needs besides the grid: the model, the viscosities, the
    padded image coordinates (perspective models) and ``2/f`` (model 2)."""

    model: int
    sx: float
    sy: float
    inv_s: float
    two_over_f: float
    xh_all: np.ndarray | None
    yh_all: np.ndarray | None


def _padded(problem: SweepProblem) -> tuple[np.ndarray, np.ndarray, _LfCoefficients]:
    """The depth padded with a frame of BIG (every cell gets four neighbours), the right-hand
    side padded alike (flat) and the Lax-Friedrichs coefficients."""
    rows, cols = problem.rhs.shape
    model = problem.model
    zp = np.full((rows + 2, cols + 2), BIG)
    zp[1:-1, 1:-1] = problem.init
    rhs = np.zeros_like(zp)
    rhs[1:-1, 1:-1] = problem.rhs
    xh_all = yh_all = None
    if model:
        assert problem.xhat is not None and problem.yhat is not None
        xg = np.zeros_like(zp)
        yg = np.zeros_like(zp)
        xg[1:-1, 1:-1] = problem.xhat[None, :]
        yg[1:-1, 1:-1] = problem.yhat[:, None]
        xh_all, yh_all = xg.ravel(), yg.ravel()
    sx, sy = problem.sigmas()
    k = _LfCoefficients(model, sx, sy, 1.0 / (sx + sy), 2.0 / float(problem.focal_px), xh_all, yh_all)
    return zp, rhs.ravel(), k


def _plans(problem: SweepProblem, lf: bool, pc: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per sweep direction: the padded flat indices of the cells it updates, by anti-diagonal,
    and where each anti-diagonal starts. Not the fixed cells; for LF only the interior (the
    edges get KOQ's rule)."""
    rows, cols = problem.rhs.shape
    upd = ~problem.fixed.copy()
    if lf and rows >= 3 and cols >= 3:
        upd[0, :] = upd[-1, :] = upd[:, 0] = upd[:, -1] = False
    elif lf:
        upd[:] = False  # too small for centred differences: only the boundary rule acts
    ii, jj = np.divmod(np.arange(rows * cols), cols)
    to_pad = (ii + 1) * pc + (jj + 1)  # grid flat index -> padded flat index
    plans = []
    for order, starts in sweep_orders(rows, cols):
        o, s = _subset(order, starts, upd.ravel())
        idx = to_pad[o]
        plans.append((idx, s))
    return plans


def _sweep(
    z: np.ndarray, idx: np.ndarray, starts: np.ndarray, pc: int, rhs: np.ndarray, lf: _LfCoefficients | None
) -> float:
    """One sweep, anti-diagonal by anti-diagonal, in place (Lax-Friedrichs with ``lf``, else
    Godunov); returns the largest decrease."""
    change = 0.0
    for a, b in zip(starts[:-1], starts[1:]):
        c = idx[a:b]
        zc = z[c]
        zw, ze = z[c - 1], z[c + 1]
        zn, zs = z[c - pc], z[c + pc]
        f = rhs[c]
        if lf is not None:
            new = _lf_update(lf, c, zc, (zw, ze, zn, zs), f)
        else:  # Godunov eikonal update (Zhao 2005, Eq. 2.3 with h = 1)
            ax = np.minimum(zw, ze)
            by = np.minimum(zn, zs)
            d = ax - by
            disc = np.maximum(2.0 * f * f - d * d, 0.0)
            new = np.where(np.abs(d) >= f, np.minimum(ax, by) + f, 0.5 * (ax + by + np.sqrt(disc)))
        new = np.minimum(zc, new)
        z[c] = new
        dmax = float(np.max(zc - new))
        if dmax > change:
            change = dmax
    return change


def _lf_update(
    k: _LfCoefficients, c: np.ndarray, zc: np.ndarray, nb: tuple[np.ndarray, ...], f: np.ndarray
) -> np.ndarray:
    """The Lax-Friedrichs update of cells ``c`` from their west, east, north, south neighbours ``nb``."""
    zw, ze, zn, zs = nb
    p = 0.5 * (ze - zw)
    q = 0.5 * (zs - zn)
    if k.model:
        xc, yc = k.xh_all[c], k.yh_all[c]  # type: ignore[index]
        h = _hamiltonian(k.model, p, q, xc, yc)
    else:
        h = np.sqrt(p * p + q * q)
    base = -h + 0.5 * k.sx * (ze + zw) + 0.5 * k.sy * (zn + zs)
    if k.model == 2:
        return _newton_falloff(zc, f, base, k.sx + k.sy, k.two_over_f)
    return (f + base) * k.inv_s


def _newton_falloff(w0: np.ndarray, k: np.ndarray, base: np.ndarray, s: float, two_over_f: float) -> np.ndarray:
    """Solve ``s·w − k·exp(−2w/f) − base = 0`` for ``w`` (LF update of model 2).

    The left side is increasing and concave in ``w``, so Newton from any start lands left of the
    root after one step and then increases monotonically to it; 4 steps reach machine precision
    from the previous iterate in practice.
    """
    w = np.minimum(w0, (base + k) / s)  # any start works; this one is close
    for _ in range(4):
        e = k * np.exp(-two_over_f * w)
        g = s * w - e - base
        w = w - g / (s + two_over_f * e)
    return w


def _koq_boundary(zp: np.ndarray, fixed_pad: np.ndarray) -> float:
    """KOQ boundary rule on the four edges of the (unpadded) grid, in place.

    ``Z₁ = min(max(2Z₂ − Z₃, Z₃), Z₁)`` along each edge's inward normal (KOQ §2; the paper's
    Alg. A2 lines 7–10 print ``max(Z₂ − Z₃)`` with the factor 2 and the second argument lost).
    Returns the largest decrease it made.
    """
    g = zp[1:-1, 1:-1]
    fx = fixed_pad[1:-1, 1:-1]
    r, c = g.shape
    change = 0.0
    if r >= 3:
        for e, a, b in ((0, 1, 2), (r - 1, r - 2, r - 3)):
            new = np.minimum(np.maximum(2.0 * g[a] - g[b], g[b]), g[e])
            new = np.where(fx[e], g[e], new)
            change = max(change, float(np.max(g[e] - new)))
            g[e] = new
    if c >= 3:
        for e, a, b in ((0, 1, 2), (c - 1, c - 2, c - 3)):
            new = np.minimum(np.maximum(2.0 * g[:, a] - g[:, b], g[:, b]), g[:, e])
            new = np.where(fx[:, e], g[:, e], new)
            change = max(change, float(np.max(g[:, e] - new)))
            g[:, e] = new
    return change
