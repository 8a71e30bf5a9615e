"""Fusion ``itof``: SFS depth + four iToF points → a metric, filtered point cloud (Algs. A3/A4).

Steps (see docs/mesh.md for the derivations and the departures from the paper):

0. **Despiking.** SFS pixels that stand out of their 3×3 median by more than ``despike_k``
   robust standard deviations are dropped (SFS outliers; the paper removes them with its filter).
1. **Anchors and metric scaling (Alg. A3).** The relative SFS depth ``z_r`` becomes metric depth
   ``Z = s·z_r + t + Σ_k w_k(pixel)·δ_k``. The global scale and offset are fitted to the valid
   iToF anchors (:func:`fit_anchors`) as a placement ``c`` (the metric depth at the anchors'
   mean SFS depth) and a log scale ratio ``u``, ``s = e^u·c/f`` (one relative unit is a pixel
   pitch at the anchors' depth), so the scale is positive by construction; weighted least squares with
   weights ``1/(σ_k² + σ_SFS²)`` (``σ_SFS`` the SFS noise estimated from the map,
   :func:`depth_noise`), a prior ``e^u ~ N(1, scale_prior_rel)`` on the scale and a Gaussian prior on
   ``c``, the set-up's working distance (``prior_distance_mm``, ± ``prior_distance_rel``): an
   anchor whose σ is far above the prior's moves nothing. Anchors whose σ is at least the
   ambiguity range/√12 (a wrapped phase that noisy is about uniform) are not used; the rest pass
   a leave-one-out outlier test (:func:`consistent_anchors`, level ``anchor_alpha``, Bonferroni
   over the anchors) against their σ plus the SFS map's relief; rejected anchors are listed with
   their reason. The record's ``worse_than_sfs`` says when the fit itself expects its placement
   to be worse than the prior's (:func:`worse_than_prior`, or as many anchors rejected as kept).
   With at least ``min_anchors_local`` anchors, and when they (not the prior) place the depth,
   each anchor's image region (Voronoi cells of the anchors, blended over ``blend_px``,
   :func:`anchor_weights`) gets a local offset ``δ_k = g_k·r_k``: its residual after the global
   fit shrunk by ``g_k = max(0, 1 − (σ_k² + σ_SFS²)/r_k²)``, so agreement within the noise
   applies nothing. Every anchor not used is warned about with its reason.
2. **Back-projection** of every valid pixel with the pinhole camera, and triangulation of the
   pixel grid (two triangles per 2×2 block of valid pixels; triangles whose longest edge exceeds
   ``max_edge_factor`` × the median are dropped: they bridge SFS outliers or depth jumps).
3. **Semi-even points on each triangle (Alg. A4, Eqs. 13–15).** ``V0`` is the triangle's vertex
   nearest its region's iToF point; ``v1, v2`` are the *unit* vectors from ``V0`` to the other two
   vertices (Eq. 13 as printed divides by ``sqrt(|V·V_ref|)``, which is not a length: we
   normalise properly); ``α = arccos(v1·v2)`` (Eq. 14); points ``P = V0 + v1·d·x + v2·(d/sin α)·y``
   with ``d·x < |V0V1|`` and ``(d/sin α)·y < |V0V2|·(1 − d·x/|V0V1|)`` (Eq. 15): rows ``d`` apart.
   ``sin α`` is floored at ``sin(min_angle_deg)`` (α → 0 makes ``d/sin α`` blow up: a sliver
   then gets only its vertex rows).
4. **Voxel merging**: points are averaged per cubic voxel of side ``voxel_mm``, by default
   ``voxel_px`` pixel pitches at the object's depth, at most 1/``min_voxels_across`` of its
   extent (a collapse is warned about).
5. **Filtering**: statistical outlier removal (mean distance to the ``knn`` nearest neighbours
   more than ``outlier_std`` standard deviations above the mean), then one implicit step of the
   heat equation on the kNN graph: ``(D + t·(D − W))·x' = D·x`` — the backward-Euler step
   ``(I + t·L_rw)·x' = x`` of ``∂x/∂τ = −L_rw x`` with the random-walk Laplacian
   ``L_rw = I − D⁻¹W`` and heat-kernel weights ``W_ij = exp(−|p_i − p_j|²/h²)`` (``h`` = mean
   neighbour distance). ``t ≤ time_step`` is dimensionless (chosen by the discrepancy principle
   against ``σ_SFS`` when ``adaptive_step``), in units of one neighbour-averaging
   step: a graph eigenmode with eigenvalue ``λ ∈ [0, 2]`` is damped by ``1/(1 + tλ)``; the step is
   unconditionally stable (implicit), so ``t`` sets the smoothing only. By default the filter
   acts on the range along each camera ray (``diffuse: range``) so the silhouette of the open
   2.5D patch does not shrink; ``diffuse: xyz`` smooths all three coordinates (paper [40]).
6. **Normals** by PCA over the ``knn`` neighbours, oriented towards the camera.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.types import Camera, DepthMap, ItofSample, PointCloud

__all__ = [
    "ItofFusion",
    "AnchorFit",
    "fit_anchors",
    "consistent_anchors",
    "worse_than_prior",
    "region_weights",
    "grid_triangles",
    "semi_even_points",
    "voxel_merge",
    "remove_outliers",
    "heat_diffusion",
    "pca_normals",
    "back_project",
    "despike",
    "depth_noise",
    "anchor_weights",
]

_MAX_POINTS = 5_000_000  # guard on Alg. A4's output (d_pitch far below the triangle size)


def _nanmedian_last(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=-1)``: per row the mean ``(lo + hi) / 2`` of the two middle sorted
    non-NaN values (the middle one twice for an odd count), as numpy computes it, NaN for an
    all-NaN row; the same values (tests/test_mesh_speed.py; a zero may differ in sign), without
    numpy's masked arrays and its one RuntimeWarning per all-NaN row (0.2 ms instead of 1.5 ms
    on the 3×3 windows of a 32² map, median of 100 calls on the 2-core box)."""
    srt = np.sort(a, axis=-1)  # NaN sort last
    cnt = (~np.isnan(a)).sum(axis=-1)
    lo = np.take_along_axis(srt, np.maximum((cnt - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(cnt // 2, 0)[..., None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore", over="ignore"):  # inf − inf, overflow: silent, as in numpy's
        mid = (lo + hi) / 2.0
    return np.where(cnt > 0, mid, np.nan)


def despike(depth: np.ndarray, valid: np.ndarray, k: float, unit: float) -> np.ndarray:
    """Valid-pixel mask without the spikes of a depth map ``(n, n)`` (any unit).

    A pixel is a spike when it differs from the median of its valid 3×3 neighbours by more than
    ``k`` robust standard deviations (1.4826 × the median absolute residual over the map), with
    the deviation floored at ``0.1·unit`` (``unit``: one pixel pitch in the map's depth unit) so
    that a noise-free surface keeps its curvature, and raised to the local scale (1.4826 × the
    median absolute residual of the 3×3 neighbourhood) so that a strongly curved region, where
    every residual is large, is kept while an isolated spike is not. Linear slopes leave no
    residual.
    """
    n0, n1 = depth.shape
    pad = np.pad(np.where(valid, depth, np.nan), 1, constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(pad, (3, 3)).reshape(n0, n1, 9)
    srt = np.sort(win, axis=-1)  # NaN sort last
    cnt = np.isfinite(win).sum(axis=-1)
    lo = np.take_along_axis(srt, np.maximum((cnt - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(cnt // 2, 0)[..., None], axis=-1)[..., 0]
    med = np.where(cnt > 0, 0.5 * (lo + hi), np.nan)  # median of the valid neighbours
    res = np.where(valid, depth - med, np.nan)
    good = np.isfinite(res)
    if not good.any():
        return valid
    sigma = max(1.4826 * float(np.median(np.abs(res[good]))), 0.1 * unit)
    # local residual scale: a smooth but strongly curved region (an occluding contour) has large
    # residuals at every pixel; a spike stands out against its own neighbourhood's too
    ares = np.pad(np.abs(res), 1, constant_values=np.nan)
    local = 1.4826 * _nanmedian_last(np.lib.stride_tricks.sliding_window_view(ares, (3, 3)).reshape(n0, n1, 9))
    scale = np.maximum(sigma, np.nan_to_num(local, nan=sigma))
    return valid & ~(np.abs(np.nan_to_num(res)) > k * scale)


def back_project(depth_m: np.ndarray, camera: Camera) -> np.ndarray:
    """Camera-frame points ``(n, n, 3)`` in metres of a z-depth map ``(n, n)`` (metres)."""
    x, y = camera.pixel_coords()
    return np.stack([x[..., 0] * depth_m, y[..., 0] * depth_m, depth_m], axis=-1)


def project_px(points_m: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel indices ``(row, col)`` of camera-frame points ``(..., 3)`` (metres);
    integer values are pixel centres."""
    p = np.asarray(points_m, dtype=np.float64)
    n, f = camera.resolution, camera.focal_px
    col = p[..., 0] / p[..., 2] * f + n / 2.0 - 0.5
    row = -p[..., 1] / p[..., 2] * f + n / 2.0 - 0.5
    return row, col


def region_weights(angles_deg: np.ndarray, anchor_angles_deg: np.ndarray, blend_deg: float) -> np.ndarray:
    """Blending weights ``(…, k)`` of the angular regions centred on ``anchor_angles_deg``.

    A pixel at polar angle ``ψ`` (degrees, about the principal point) belongs to the region of
    the nearest anchor angle. With ``blend_deg = b > 0`` the weights ramp linearly over a band of
    ``b`` degrees centred on each border (45° from the anchors when they are 90° apart), so the
    per-region offsets do not leave steps; ``b = 0`` gives hard regions (the paper). Weights are
    non-negative and sum to 1.
    """
    a = np.asarray(angles_deg, dtype=np.float64)[..., None]
    delta = np.abs((a - np.asarray(anchor_angles_deg)[None, :] + 180.0) % 360.0 - 180.0)
    nearest = np.argmin(delta, axis=-1)
    hard = np.zeros(delta.shape)
    np.put_along_axis(hard, nearest[..., None], 1.0, axis=-1)
    if blend_deg <= 0:
        return hard
    half = 180.0 / len(anchor_angles_deg)  # 45° for four anchors
    w = np.clip((half + 0.5 * blend_deg - delta) / blend_deg, 0.0, 1.0)
    s = w.sum(axis=-1, keepdims=True)
    return np.where(s > 0, w / np.where(s > 0, s, 1.0), hard)


#: Bounds of the fitted log scale ratio ``u = ln(s / s_ref)``: the scale stays within a factor
#: 1e6 of the geometric one (assumed: far beyond any SFS scale error; keeps the solver finite
#: when anchors without a scale prior pull the scale towards 0 or a sign flip).
_LOG_RATIO_BOUND = float(np.log(1e6))


@dataclass(frozen=True)
class AnchorFit:
    """The anchors' fit of Alg. A3 (:func:`fit_anchors`).

    Attributes:
        scale: ``s`` (metres per SFS unit), > 0 by construction (``s = e^u · s_ref``).
        offset_m: ``t`` (metres), so that ``z = s·zr + t``.
        placement_m: ``c``, the metric depth at the reference SFS depth ``ref_zr`` (metres, > 0).
        placement_sigma_m: the fit's standard deviation of ``c`` (metres; from the Jacobian).
        scale_ref: ``s_ref``, the geometric scale at the placement (``c / focal_px``; 1 for
            metric SFS depth).
        chi2: the fit's χ², anchors and priors (dimensionless).
        dof: its degrees of freedom, anchors + priors − 2.
        anchor_chi2: the anchors' part of ``chi2``.
        cov: ``(2, 2)`` covariance of ``(u, ln c)``.
    """

    scale: float
    offset_m: float
    placement_m: float
    placement_sigma_m: float
    scale_ref: float
    chi2: float
    dof: int
    anchor_chi2: float
    cov: np.ndarray

    def predict(self, zr: np.ndarray, ref_zr: float, focal_px: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Metric depth at relative depths ``zr`` and its variance from the fit (metres, m²)."""
        zr = np.asarray(zr, dtype=np.float64)
        b = zr - ref_zr
        pred = self.scale * zr + self.offset_m
        # gradient of pred = c + e^u·s_ref(c)·b in (u, ln c): s·b, and c + s·b (s_ref = c/f) or c (1)
        dv = self.placement_m + (self.scale * b if focal_px is not None else np.zeros_like(b))
        g0, g1 = self.scale * b, dv  # written out: no BLAS kernel may change its bits
        var = g0 * g0 * self.cov[0, 0] + 2.0 * g0 * g1 * self.cov[0, 1] + g1 * g1 * self.cov[1, 1]
        return pred, np.maximum(var, 0.0)


def _inv_sym2(a: float, b: float, d: float) -> np.ndarray:
    """The (pseudo-)inverse of the symmetric 2×2 matrix ``[[a, b], [b, d]]``, in closed form
    (no LAPACK: its result must not depend on the BLAS kernels, see docs/sweeps.md)."""
    tr, det = a + d, a * d - b * b
    if not tr > 0:
        return np.zeros((2, 2))
    big = 0.5 * (tr + math.hypot(a - d, 2.0 * b))  # the larger eigenvalue; the smaller is det/big
    if det > 1e-15 * big * big:  # numpy.linalg.pinv's default cut-off (rcond=1e-15)
        return np.array([[d / det, -b / det], [-b / det, a / det]])
    # rank 1 within that cut-off: the pseudo-inverse v·vᵀ/λ of the one eigenpair, λ ≈ tr
    return np.array([[a, b], [b, d]]) / tr**2


def _levenberg_marquardt(
    fun: Callable[[tuple[float, float]], tuple[np.ndarray, np.ndarray, np.ndarray]],
    x0: tuple[float, float],
    u_bound: float,
    v_max: float,
    max_iter: int = 200,
) -> tuple[float, float]:
    """Minimise ``Σ r²`` over two parameters ``(u, v)``, ``|u| ≤ u_bound``, ``v ≤ v_max``, by
    Levenberg–Marquardt with Marquardt's diagonal scaling (Nocedal & Wright, *Numerical
    Optimization*, 2nd ed., §10.3), steps projected onto the bounds. ``fun`` returns the
    residuals and their derivatives in ``u`` and ``v``.

    Written out with elementwise numpy and sums only, so that the fit gives the same bits under
    every OpenBLAS/LAPACK kernel set (``scipy.optimize.least_squares`` did not: its last bits
    moved the fused cloud of one CI job, docs/sweeps.md)."""

    def clip(u: float, v: float) -> tuple[float, float]:
        return min(max(u, -u_bound), u_bound), min(v, v_max)

    x = clip(*x0)
    r, ju, jv = fun(x)
    cost = float(np.sum(r * r))
    lam = 1e-3
    for _ in range(max_iter):
        a, b, d = float(np.sum(ju * ju)), float(np.sum(ju * jv)), float(np.sum(jv * jv))
        gu, gv = float(np.sum(ju * r)), float(np.sum(jv * r))
        if not (math.isfinite(cost) and math.isfinite(a + b + d + gu + gv)):
            break
        if abs(gu) + abs(gv) <= 1e-15 * max(cost, 1e-300) ** 0.5 * (math.sqrt(a) + math.sqrt(d) + 1e-300):
            break
        improved = False
        while lam < 1e16:
            a2, d2 = a + lam * max(a, 1e-300), d + lam * max(d, 1e-300)
            det = a2 * d2 - b * b
            if not det > 0:
                lam *= 10.0
                continue
            du, dv = (-d2 * gu + b * gv) / det, (b * gu - a2 * gv) / det
            x_new = clip(x[0] + du, x[1] + dv)
            r_new, ju_new, jv_new = fun(x_new)
            cost_new = float(np.sum(r_new * r_new))
            if math.isfinite(cost_new) and cost_new <= cost:
                step = abs(x_new[0] - x[0]) + abs(x_new[1] - x[1])
                gain = cost - cost_new
                x, r, ju, jv, cost = x_new, r_new, ju_new, jv_new, cost_new
                lam = max(lam / 10.0, 1e-12)
                improved = step > 1e-14 * (1.0 + abs(x[0]) + abs(x[1])) and gain > 1e-15 * max(cost, 1e-300)
                break
            lam *= 10.0
        if not improved:
            break
    return x


def fit_anchors(
    zr: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    ref_zr: float,
    focal_px: float | None,
    scale_prior_rel: float | None,
    prior_m: float | None = None,
    prior_sigma_m: float | None = None,
) -> AnchorFit:
    """Alg. A3's global fit ``z ≈ s·zr + t`` to the anchors, weighted by their noise, with the
    scale positive by construction.

    The unknowns are the placement ``c`` (metric depth at the SFS depth ``ref_zr``) and the
    log scale ratio ``u``: ``s = e^u · s_ref``, ``s_ref = c / focal_px`` (one relative SFS unit
    is a pixel pitch at the object's depth; ``focal_px=None``: metric SFS depth, ``s_ref = 1``),
    ``t = c − s·ref_zr``. Minimised (Levenberg–Marquardt, :func:`_levenberg_marquardt`, ``u``
    bounded to a factor 1e6):

        Σ_i ((ẑ_i − z_i)/σ_i)² + ((e^u − 1) / scale_prior_rel)² + ((c − prior_m)/prior_sigma_m)²

    the last two terms only when given: a Gaussian prior on the scale ratio ``e^u`` (positive
    by construction, so it is never overruled into
    a sign flip) and a Gaussian prior on the placement (the set-up's working distance). An
    anchor whose ``σ`` is far above the prior's moves nothing.

    Args:
        zr: ``(k,)`` relative SFS depth at the anchors.
        z: ``(k,)`` iToF z-depth of the anchors, metres.
        sigma: ``(k,)`` anchor standard deviations, metres (finite, > 0).
        ref_zr: the reference relative depth of the placement (the caller: the anchors' mean SFS
            depth, so ``c/f`` is the pixel pitch at their depth).
        focal_px: focal length in pixels (relative SFS depth), or None (metric SFS depth).
        scale_prior_rel: standard deviation of ``u`` (≈ the relative tolerance of the scale);
            None = no scale prior (needs anchors at two SFS depths).
        prior_m, prior_sigma_m: the placement prior, metres; None = none.

    Raises:
        NirspiError: no anchor, or anchors that cannot determine the scale without its prior.
    """
    zr = np.asarray(zr, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    sig = np.asarray(sigma, dtype=np.float64)
    k = len(z)
    has_prior = prior_m is not None and prior_sigma_m is not None and prior_sigma_m > 0
    if k == 0 and not has_prior:
        raise NirspiError("fusion: no valid iToF anchor on the SFS depth map; cannot make it metric")
    if k == 0 and scale_prior_rel is None:
        scale_prior_rel = 0.2  # no anchor: the scale is the geometric one, as with one anchor
    if scale_prior_rel is None and (k < 2 or float(np.ptp(zr)) <= 0):
        raise NirspiError(
            f"fusion: the {k} iToF anchor(s) cannot determine the depth scale and offset "
            "(anchors at equal SFS depth?); set fusion.scale_prior_rel"
        )
    b = zr - ref_zr
    rel = focal_px is not None
    f_px = float(focal_px) if focal_px is not None else 1.0

    sp = None if scale_prior_rel is None else float(scale_prior_rel)
    pm = float(prior_m) if has_prior else 0.0  # type: ignore[arg-type]
    ps = float(prior_sigma_m) if has_prior else 1.0  # type: ignore[arg-type]

    def residuals(x: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals and their derivatives in ``u`` and ``ln c`` (analytic)."""
        eu, c = math.exp(x[0]), math.exp(x[1])
        s = eu * (c / f_px if rel else 1.0)
        r, du, dv = [(c + s * b - z) / sig], [s * b / sig], [(c + s * b if rel else c + 0.0 * b) / sig]
        if sp is not None:  # ratio e^u ~ N(1, rel), > 0
            r.append(np.array([math.expm1(x[0]) / sp]))
            du.append(np.array([eu / sp]))
            dv.append(np.zeros(1))
        if has_prior:
            r.append(np.array([(c - pm) / ps]))
            du.append(np.zeros(1))
            dv.append(np.array([c / ps]))
        return np.concatenate(r), np.concatenate(du), np.concatenate(dv)

    # start: u = 0 and the weighted least-squares placement at that scale (closed form)
    w = 1.0 / sig**2
    a = 1.0 + b / f_px if rel else np.ones(k)
    shift = np.zeros(k) if rel else b
    num = float(np.sum(w * a * (z - shift)))
    den = float(np.sum(w * a * a))
    if has_prior:
        num += pm / ps**2
        den += 1.0 / ps**2
    c0 = num / den if den > 0 and np.isfinite(num / den) else float(np.median(z))
    c0 = max(c0, 1e-9 * max(float(np.max(np.abs(z), initial=0.0)), 1e-3))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        x = _levenberg_marquardt(residuals, (0.0, math.log(c0)), _LOG_RATIO_BOUND, math.log(1e12))
        res, ju, jv = residuals(x)
        cov = _inv_sym2(float(np.sum(ju * ju)), float(np.sum(ju * jv)), float(np.sum(jv * jv)))
    u, v = x
    c = math.exp(v) if v < 709.0 else math.inf
    s_ref = c / f_px if rel else 1.0
    s = math.exp(u) * s_ref
    if not (np.isfinite(s) and np.isfinite(c) and np.all(np.isfinite(res)) and np.all(np.isfinite(cov))):
        raise NirspiError("fusion: the anchors' fit of the depth scale and offset did not converge to finite values")
    return AnchorFit(
        scale=s,
        offset_m=float(c - s * ref_zr),
        placement_m=c,
        placement_sigma_m=float(c * np.sqrt(max(cov[1, 1], 0.0))),
        scale_ref=float(s_ref),
        chi2=float(np.sum(res**2)),
        dof=int(len(res) - 2),
        anchor_chi2=float(np.sum(res[:k] ** 2)),
        cov=cov,
    )


def consistent_anchors(
    zr: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    alpha: float | None,
    fit: Callable[[np.ndarray], AnchorFit],
    ref_zr: float,
    focal_px: float | None,
    tau_m: float = 0.0,
) -> tuple[np.ndarray, dict[int, str], AnchorFit]:
    """The anchors that pass an outlier test, the rejected ones with their reason, and the final
    fit.

    Each anchor is predicted from the others (leave-one-out fit, weighted by ``sigma``) and its
    squared standardised deviation ``d² = (z_i − ẑ_i)² / (σ_i² + τ² + var(ẑ_i))`` is compared
    with the χ²₁ quantile at ``alpha / k`` (the outlier test on externally studentised residuals
    with a Bonferroni bound over the ``k`` anchors: Cook & Weisberg, *Residuals and Influence in
    Regression*, 1982, §2.2.2; Weisberg, *Applied Linear Regression*, 4th ed., §9.1.2). ``τ``
    (``tau_m``) is the SFS map's own shape error at an anchor, which the local offsets absorb
    (the caller passes the map's relief: an anchor within it can be a local SFS error, not a bad
    anchor). The farthest anchor beyond the bound is rejected, the rest refitted and tested
    again; the family-wise chance of rejecting a good anchor is at most ``alpha``.
    ``alpha=None``: no test. ``fit(idx)`` fits the anchors ``idx`` (indices into the arrays).
    """
    from scipy.stats import chi2 as chi2_dist  # start-up: loads scipy.stats (only for the test)

    keep = np.arange(len(z))
    rejected: dict[int, str] = {}
    cur = fit(keep)
    while alpha is not None and len(keep) >= 2:
        worst, worst_d2, worst_dev = -1, 0.0, 0.0
        for j in keep:
            try:
                loo = fit(keep[keep != j])
            except NirspiError:
                continue
            pred, var = loo.predict(zr[j : j + 1], ref_zr, focal_px)
            d2 = float((z[j] - pred[0]) ** 2 / (sigma[j] ** 2 + tau_m**2 + var[0]))
            if d2 > worst_d2:
                worst, worst_d2, worst_dev = int(j), d2, float(z[j] - pred[0])
        limit = float(chi2_dist.ppf(1.0 - alpha / len(keep), 1))
        if worst < 0 or worst_d2 <= limit:
            break
        rejected[worst] = (
            f"inconsistent: {abs(worst_dev):.3g} m "
            f"from the depth the other anchors and the SFS shape predict there, {np.sqrt(worst_d2):.1f} times its "
            f"sigma with the SFS relief (limit {np.sqrt(limit):.2f}: outlier test at alpha={alpha:g}, Bonferroni over "
            f"{len(keep)} anchors)"
        )
        keep = keep[keep != worst]
        cur = fit(keep)
    return keep, rejected, cur


def worse_than_prior(cur: AnchorFit, prior_sigma_m: float | None, n_anchors: int, scale_prior: bool) -> str | None:
    """Why the fused placement is expected to be worse than SFS placed by the prior alone, or
    None. No ground truth: from the fit's own numbers.

    The fit weighs the anchors by their stated σ: its placement is ``c = w·c_a + (1 − w)·c_p``
    with the anchors' share ``w = 1 − σ_c² / σ_p²`` (``σ_c`` the fitted placement's standard
    deviation, ``σ_p`` the prior's). If the anchors in fact scatter ``R`` times more than their σ
    (``R² = χ²_anchors / dof``, the Birge ratio, floored at 1; ``dof = k − 1`` with a scale prior,
    ``k − 2`` without), the placement's mean square error is ``w²R²σ_a² + (1 − w)²σ_p²``
    (``σ_a² = σ_c² / w`` the anchors' own variance), against ``σ_p²`` for the prior alone: it is
    larger exactly when ``R² > 2 + σ_p²/σ_a²``."""
    if prior_sigma_m is None or not prior_sigma_m > 0:
        return None
    dof = n_anchors - (1 if scale_prior else 2)
    if dof < 1:
        return None
    r2 = max(1.0, cur.anchor_chi2 / dof)
    share = 1.0 - (cur.placement_sigma_m / prior_sigma_m) ** 2
    if not share > 0:
        return None
    var_a = cur.placement_sigma_m**2 / share
    if r2 > 2.0 + prior_sigma_m**2 / var_a:
        return (
            f"the {n_anchors} anchors scatter {np.sqrt(r2):.3g} times their stated sigma (chi2 {cur.anchor_chi2:.3g} "
            f"on {dof} dof), so the placement they carry (weight {share:.2f}) is expected to be worse than the "
            f"working-distance prior's ({prior_sigma_m * 1e3:.3g} mm): limit {np.sqrt(2.0 + prior_sigma_m**2 / var_a):.3g}"
        )
    return None


def grid_triangles(valid: np.ndarray) -> np.ndarray:
    """Triangles ``(f, 3)`` of flat pixel indices over the valid pixels of an ``(h, w)`` grid:
    two per 2×2 block, kept when all three corners are valid (counter-clockwise seen from the
    camera)."""
    h, w = valid.shape
    idx = np.arange(h * w).reshape(h, w)
    a, b = idx[:-1, :-1], idx[:-1, 1:]  # top-left, top-right
    c, d = idx[1:, :-1], idx[1:, 1:]  # bottom-left, bottom-right
    va, vb, vc, vd = valid[:-1, :-1], valid[:-1, 1:], valid[1:, :-1], valid[1:, 1:]
    t1 = np.stack([a, c, b], axis=-1)[va & vc & vb]
    t2 = np.stack([b, c, d], axis=-1)[vb & vc & vd]
    return np.concatenate([t1, t2]).reshape(-1, 3)


def semi_even_points(tri: np.ndarray, ref: np.ndarray, d_pitch_m: float, min_angle_deg: float = 1.0) -> np.ndarray:
    """Alg. A4: semi-even points at pitch ``d`` on each triangle (Eqs. 13–15), metres.

    Args:
        tri: ``(f, 3, 3)`` triangle vertices, metres.
        ref: ``(f, 3)`` reference point of each triangle (its region's iToF point); ``V0`` is
            the vertex nearest to it.
        d_pitch_m: point pitch ``d``, metres (> 0).
        min_angle_deg: floor of α in Eq. (15) (``d/sin α`` guard), degrees.

    Returns:
        ``(p, 3)`` points: the lattice ``V0 + v1·d·x + v2·(d/sin α)·y`` inside each triangle
        (always including ``V0``). Degenerate triangles (a zero edge) give ``V0`` only.
    """
    tri = np.asarray(tri, dtype=np.float64)
    if len(tri) == 0:
        return np.zeros((0, 3))
    first = np.argmin(np.linalg.norm(tri - ref[:, None, :], axis=-1), axis=1)
    order = (first[:, None] + np.arange(3)[None, :]) % 3
    tri = np.take_along_axis(tri, order[..., None], axis=1)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    l1, l2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
    ok = (l1 > 0) & (l2 > 0)
    safe1, safe2 = np.where(ok, l1, 1.0), np.where(ok, l2, 1.0)
    u1, u2 = e1 / safe1[:, None], e2 / safe2[:, None]  # Eq. (13), unit vectors
    cos_a = np.clip(np.einsum("ij,ij->i", u1, u2), -1.0, 1.0)
    sin_a = np.sqrt(1.0 - cos_a**2)  # sin(arccos(·)), Eq. (14)
    d1 = d_pitch_m
    d2 = d_pitch_m / np.maximum(sin_a, np.sin(np.deg2rad(min_angle_deg)))  # Eq. (15), α guarded
    nx = np.where(ok, np.ceil(safe1 / d1), 1).astype(np.int64)
    ny = np.where(ok, np.ceil(safe2 / d2), 1).astype(np.int64)
    counts = nx * ny
    total = int(counts.sum())
    if total > _MAX_POINTS:  # a property of the data (how far the surface spans), not of the config
        span = float(np.linalg.norm(np.ptp(tri.reshape(-1, 3), axis=0)))
        raise NirspiError(
            f"fusion: the fused surface spans {span:.3g} m ({len(tri)} triangles), so Alg. A4 at a "
            f"{d_pitch_m * 1e3:g} mm pitch would need {total} points (more than {_MAX_POINTS}); the metric "
            "depth is implausible for a camera-scale object (hint: a coarser fusion.d_pitch_mm)"
        )
    t_idx = np.repeat(np.arange(len(tri)), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    local = np.arange(total) - start
    x = local // ny[t_idx]
    y = local % ny[t_idx]
    s = d1 * x / safe1[t_idx]
    keep = (y == 0) | (d2[t_idx] * y < safe2[t_idx] * (1.0 - s))  # Eq. (15) bounds
    keep &= ok[t_idx] | ((x == 0) & (y == 0))
    t_idx, x, y = t_idx[keep], x[keep], y[keep]
    return v0[t_idx] + u1[t_idx] * (d1 * x)[:, None] + u2[t_idx] * (d2[t_idx] * y)[:, None]


def voxel_merge(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Average the points ``(p, 3)`` (metres) falling in each cubic voxel of side ``voxel_m``."""
    if len(points) == 0:
        return points.reshape(0, 3)
    q = np.floor(points / voxel_m).astype(np.int64)
    q -= q.min(axis=0)
    dims = q.max(axis=0) + 1
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    out = np.stack([np.bincount(inv, weights=points[:, i]) for i in range(3)], axis=1)
    return out / cnt[:, None]


def remove_outliers(points: np.ndarray, knn: int, n_std: float) -> np.ndarray:
    """Boolean mask ``(p,)`` of the points kept by statistical outlier removal (Rusu et al.
    2008): drop points whose mean distance to their ``knn`` neighbours exceeds the mean of that
    quantity by more than ``n_std`` standard deviations."""
    p = len(points)
    if p <= knn + 1:
        return np.ones(p, dtype=bool)
    dist, _ = cKDTree(points).query(points, k=knn + 1)
    mean_d = dist[:, 1:].mean(axis=1)
    return mean_d <= mean_d.mean() + n_std * mean_d.std()


def _knn_graph(points: np.ndarray, knn: int) -> sparse.csr_matrix:
    """Symmetric heat-kernel weight matrix of the kNN graph, ``exp(−d²/h²)``, ``h`` = mean
    neighbour distance."""
    p = len(points)
    k = min(knn, p - 1)
    dist, idx = cKDTree(points).query(points, k=k + 1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    h = float(dist.mean()) if dist.size and dist.mean() > 0 else 1.0
    w = np.exp(-((dist / h) ** 2))
    rows = np.repeat(np.arange(p), k)
    mat = sparse.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(p, p))
    return mat.maximum(mat.T).tocsr()


def heat_diffusion(values: np.ndarray, points: np.ndarray, knn: int, time_step: float) -> np.ndarray:
    """One implicit heat-equation step of ``values`` ``(p,)`` or ``(p, c)`` on the kNN graph of
    ``points`` ``(p, 3)``: solves ``(D + t(D − W)) x' = D x`` (backward Euler of
    ``∂x/∂τ = −(I − D⁻¹W)x``), unconditionally stable; ``t = time_step`` is dimensionless.
    Units of ``values`` are kept."""
    if time_step == 0 or len(points) < 3:
        return np.array(values, dtype=np.float64, copy=True)
    return _heat_step(values, *_heat_graph(points, knn), time_step)


def _heat_graph(points: np.ndarray, knn: int) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The kNN heat-kernel graph ``W`` of ``points`` ``(p, 3)`` (metres) and its degrees
    ``D`` ``(p,)`` (dimensionless, floored at 1e-12: an isolated point stays put), which
    :func:`heat_diffusion` uses for any ``t``: :meth:`ItofFusion._diffuse` builds them once for
    its up to three trial steps."""
    w = _knn_graph(points, knn)
    deg = np.asarray(w.sum(axis=1)).ravel()
    return w, np.maximum(deg, 1e-12)


def _heat_step(values: np.ndarray, w: sparse.csr_matrix, deg: np.ndarray, time_step: float) -> np.ndarray:
    """Solve ``(D + t(D − W)) x' = D x`` for ``values`` ``(p,)`` or ``(p, c)`` on the graph of
    :func:`_heat_graph` (``t = time_step`` > 0, dimensionless); units of ``values`` are kept."""
    p = len(deg)
    d = sparse.diags(deg)
    a = ((1.0 + time_step) * d - time_step * w).tocsc()
    rhs = deg[:, None] * np.asarray(values, dtype=np.float64).reshape(p, -1)
    out = spsolve(a, rhs)
    return np.asarray(out).reshape(np.shape(values))


def pca_normals(points: np.ndarray, knn: int) -> np.ndarray:
    """Unit normals ``(p, 3)`` by PCA of the ``knn`` nearest neighbours, oriented towards the
    camera at the origin (``n · p < 0``)."""
    p = len(points)
    if p < 3:
        return np.tile([0.0, 0.0, -1.0], (p, 1))
    k = min(knn, p)
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]  # (p, k, 3)
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("pki,pkj->pij", c, c)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    n *= np.where(np.einsum("ij,ij->i", n, points) > 0, -1.0, 1.0)[:, None]
    return n


def depth_noise(depth: np.ndarray, valid: np.ndarray) -> float:
    """Robust estimate of the white-noise standard deviation of a depth map ``(n, n)`` (its unit).

    The residual of each valid pixel against the mean of its four valid neighbours has standard
    deviation ``σ·sqrt(1 + 1/4)`` for white noise ``σ`` and no residual on a plane; we take
    1.4826 × its median absolute value / 1.118 (a smooth surface adds only its small curvature
    term, ``pitch²·κ/2``). Returns 0 when fewer than 9 pixels have four valid neighbours.
    """
    z = np.where(valid, depth, 0.0)
    v = valid.astype(np.float64)
    zp, vp = np.pad(z, 1), np.pad(v, 1)
    nsum = zp[:-2, 1:-1] + zp[2:, 1:-1] + zp[1:-1, :-2] + zp[1:-1, 2:]
    ncnt = vp[:-2, 1:-1] + vp[2:, 1:-1] + vp[1:-1, :-2] + vp[1:-1, 2:]
    inner = valid & (ncnt == 4)
    if inner.sum() < 9:
        return 0.0
    res = (z - nsum / np.maximum(ncnt, 1))[inner]
    return float(1.4826 * np.median(np.abs(res - np.median(res))) / np.sqrt(1.25))


def anchor_weights(rows: np.ndarray, cols: np.ndarray, anchor_rc: np.ndarray, blend_px: float) -> np.ndarray:
    """Weights ``(…, k)`` of the anchors' image regions at pixels ``(rows, cols)``: Voronoi cells
    of the anchors' pixel positions ``anchor_rc`` ``(k, 2)``, blended over a band ``blend_px``
    wide around each cell border (``w_k ∝ clip((d_min + blend/2 − d_k)/blend, 0, 1)``, the same
    linear ramp as :func:`region_weights`); non-negative, summing to 1."""
    d = np.hypot(rows[..., None] - anchor_rc[:, 0], cols[..., None] - anchor_rc[:, 1])
    hard = np.zeros(d.shape)
    np.put_along_axis(hard, np.argmin(d, axis=-1)[..., None], 1.0, axis=-1)
    if blend_px <= 0 or anchor_rc.shape[0] == 1:
        return hard
    dmin = d.min(axis=-1, keepdims=True)
    w = np.clip((dmin + 0.5 * blend_px - d) / blend_px, 0.0, 1.0)
    tot = w.sum(axis=-1, keepdims=True)
    return np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), hard)


@dataclass(frozen=True)
class ItofFusion:
    """Fusion ``itof``: Algorithms A3/A4 with voxel merging and a heat-diffusion filter.

    Attributes:
        d_pitch_mm: point pitch of Alg. A4, mm (paper: 5 mm).
        voxel_mm: voxel side for merging, mm; null = ``voxel_px`` pixel pitches at the object's
            median depth, at most ``1/min_voxels_across`` of the object's extent.
        voxel_px: the automatic voxel in pixel pitches at the object's median depth.
        min_voxels_across: the automatic voxel keeps at least this many voxels across the
            object's smaller image extent (a near or small object never collapses).
        min_angle_deg: floor on α in Eq. (15) (guard of ``d/sin α``), degrees.
        scale_prior_rel: relative tolerance of the prior scale ``Z̄/f`` (SFS in pixel-pitch
            units); null = fit the scale from the anchors alone (needs anchors at different SFS
            depths).
        prior_distance_mm: the set-up's working distance, mm: a Gaussian prior on the depth of
            the anchors' mean SFS depth (``conf/fusion/itof.yaml``: the scene's ``distance_mm``, the
            same nominal distance the metrics' geometric SFS baseline assumes); null = none
            (the anchors alone place the depth).
        prior_distance_rel: its relative standard deviation (assumed 0.25: the paper's objects
            stand at 20 cm in a 35 cm chamber, ±5 cm).
        anchor_alpha: level of the χ² test of the anchors' consistency (an anchor beyond its
            noise of the others' prediction is rejected, :func:`consistent_anchors`); null = no
            test.
        local_offsets: with at least ``min_anchors_local`` valid anchors, each anchor's image
            region gets its own offset: the anchor's residual after the global fit, shrunk by
            how well SFS and iToF already agree there (module docstring).
        min_anchors_local: fewest valid anchors for local offsets (below: scale and offset only).
        blend_px: band (pixels) over which neighbouring anchor regions' offsets blend.
        anchor_radius_px: an iToF spot off the SFS mask is matched to the nearest valid pixel
            within this radius (pixels), else it is not used.
        despike_k: drop SFS pixels farther than this many robust standard deviations from the
            median of their 3×3 neighbours (SFS outliers) before anything else; null = off.
        max_edge_factor: drop grid triangles whose longest edge exceeds this × the median.
        knn: neighbours for the outlier test, the diffusion graph and the normals.
        outlier_std: statistical outlier threshold in standard deviations; null = off.
        time_step: largest dimensionless implicit heat-diffusion step ``t`` (0 = no smoothing).
        adaptive_step: shrink ``t`` by the discrepancy principle so that the filter moves the
            points by no more than the estimated SFS noise (noise-free depth stays put).
        diffuse: ``range`` (along camera rays; keeps the silhouette) or ``xyz``.
    """

    d_pitch_mm: float = 5.0
    voxel_mm: float | None = None
    voxel_px: float = 2.0
    min_voxels_across: int = 16
    min_angle_deg: float = 1.0
    scale_prior_rel: float | None = 0.2
    prior_distance_mm: float | None = None
    prior_distance_rel: float = 0.25
    anchor_alpha: float | None = 0.01
    local_offsets: bool = True
    min_anchors_local: int = 3
    blend_px: float = 8.0
    anchor_radius_px: float = 2.0
    despike_k: float | None = 4.0
    max_edge_factor: float = 4.0
    knn: int = 8
    outlier_std: float | None = 2.5
    time_step: float = 8.0
    adaptive_step: bool = True
    diffuse: str = "range"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.d_pitch_mm) and self.d_pitch_mm > 0):
            raise ConfigError("d_pitch_mm", self.d_pitch_mm, "a pitch in mm > 0")
        if self.voxel_mm is not None and not (np.isfinite(self.voxel_mm) and self.voxel_mm > 0):
            raise ConfigError("voxel_mm", self.voxel_mm, "a voxel size in mm > 0, or null (automatic)")
        if not (np.isfinite(self.voxel_px) and self.voxel_px > 0):
            raise ConfigError("voxel_px", self.voxel_px, "pixel pitches > 0")
        if int(self.min_voxels_across) != self.min_voxels_across or not 2 <= self.min_voxels_across <= 4096:
            raise ConfigError("min_voxels_across", self.min_voxels_across, "an integer from 2 to 4096")
        if not 0.0 < self.min_angle_deg < 90.0:
            raise ConfigError("min_angle_deg", self.min_angle_deg, "degrees in (0, 90)")
        if self.scale_prior_rel is not None and not (np.isfinite(self.scale_prior_rel) and self.scale_prior_rel > 0):
            raise ConfigError("scale_prior_rel", self.scale_prior_rel, "a relative tolerance > 0, or null")
        if self.prior_distance_mm is not None and not (
            np.isfinite(self.prior_distance_mm) and self.prior_distance_mm > 0
        ):
            raise ConfigError("prior_distance_mm", self.prior_distance_mm, "a distance in mm > 0, or null")
        if not (np.isfinite(self.prior_distance_rel) and self.prior_distance_rel > 0):
            raise ConfigError("prior_distance_rel", self.prior_distance_rel, "a relative tolerance > 0")
        if self.anchor_alpha is not None and not 0.0 < self.anchor_alpha < 1.0:
            raise ConfigError("anchor_alpha", self.anchor_alpha, "a test level in (0, 1), or null (no test)")
        if not isinstance(self.local_offsets, bool):
            raise ConfigError("local_offsets", self.local_offsets, "true or false")
        if int(self.min_anchors_local) != self.min_anchors_local or not 1 <= self.min_anchors_local <= 64:
            raise ConfigError("min_anchors_local", self.min_anchors_local, "an integer from 1 to 64")
        if not (np.isfinite(self.blend_px) and self.blend_px >= 0):
            raise ConfigError("blend_px", self.blend_px, "pixels >= 0")
        if not self.anchor_radius_px >= 0:
            raise ConfigError("anchor_radius_px", self.anchor_radius_px, "pixels >= 0")
        if self.despike_k is not None and not self.despike_k > 0:
            raise ConfigError("despike_k", self.despike_k, "standard deviations > 0, or null")
        if not self.max_edge_factor > 1:
            raise ConfigError("max_edge_factor", self.max_edge_factor, "a factor > 1")
        if int(self.knn) != self.knn or not 3 <= self.knn <= 64:
            raise ConfigError("knn", self.knn, "an integer from 3 to 64")
        if self.outlier_std is not None and not self.outlier_std > 0:
            raise ConfigError("outlier_std", self.outlier_std, "standard deviations > 0, or null")
        if not (np.isfinite(self.time_step) and self.time_step >= 0):
            raise ConfigError("time_step", self.time_step, "a dimensionless step >= 0")
        if not isinstance(self.adaptive_step, bool):
            raise ConfigError("adaptive_step", self.adaptive_step, "true or false")
        if self.diffuse not in ("range", "xyz"):
            raise ConfigError("diffuse", self.diffuse, "range or xyz")

    # -- Alg. A3: anchors and metric depth ---------------------------------------------------
    def _anchor_values(
        self, zr_map: np.ndarray, valid: np.ndarray, itof: ItofSample, camera: Camera
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
        """Per anchor: ``(used, zr, z_m, sigma_m, reasons)``; every unusable anchor is warned
        about and its reason listed (``""`` for a used one)."""
        pts = np.asarray(itof.points_m, dtype=np.float64).reshape(-1, 3)
        sig = np.asarray(itof.sigma_m, dtype=np.float64).reshape(-1)
        n = camera.resolution
        used = np.zeros(len(pts), dtype=bool)
        zr = np.zeros(len(pts))
        reasons = [""] * len(pts)
        rr, cc = np.nonzero(valid)
        for k, (p, s) in enumerate(zip(pts, sig)):
            if not (np.all(np.isfinite(p)) and p[2] > 0 and np.isfinite(s) and s > 0):
                reasons[k] = f"no valid range (sigma={s:.3g} m)"
            else:
                row, col = project_px(p, camera)
                r0, c0 = int(np.floor(row)), int(np.floor(col))
                if 0 <= r0 < n - 1 and 0 <= c0 < n - 1 and valid[r0 : r0 + 2, c0 : c0 + 2].all():
                    fr, fc = row - r0, col - c0
                    b = zr_map[r0 : r0 + 2, c0 : c0 + 2]
                    zr[k] = (
                        b[0, 0] * (1 - fr) * (1 - fc)
                        + b[0, 1] * (1 - fr) * fc
                        + b[1, 0] * fr * (1 - fc)
                        + b[1, 1] * fr * fc
                    )
                    used[k] = True
                    continue
                d2 = (rr - row) ** 2 + (cc - col) ** 2 if len(rr) else np.zeros(0)
                j = int(np.argmin(d2)) if len(d2) else -1
                if j >= 0 and d2[j] <= self.anchor_radius_px**2:
                    zr[k], used[k] = zr_map[rr[j], cc[j]], True
                    continue
                near = f"{np.sqrt(d2[j]):.1f} px" if j >= 0 else "no valid pixel"
                reasons[k] = (
                    f"falls at pixel ({row:.1f}, {col:.1f}), outside the SFS depth mask (nearest valid "
                    f"pixel {near} > anchor_radius_px={self.anchor_radius_px:g})"
                )
            warnings.warn(f"fusion: iToF spot {k} not used: {reasons[k]}", stacklevel=3)
        return used, zr, pts[:, 2], sig, reasons

    def metric_depth(self, depth: DepthMap, itof: ItofSample, camera: Camera) -> tuple[np.ndarray, np.ndarray, dict]:
        """Alg. A3: the metric z-depth map ``(n, n)`` (metres, valid where the returned mask is
        True) and the fit ``{scale, offset_m, region_offsets_m, anchors_used, …}``.

        Degrees of freedom by the number of valid anchors: 1 → the offset (the scale is the prior
        ``Z̄/f``); 2 → offset and scale (with the prior); ≥ ``min_anchors_local`` (3) → also one
        local offset per anchor region, shrunk towards 0 where SFS and iToF agree within their
        combined uncertainty."""
        zr_map = np.asarray(depth.depth_m, dtype=np.float64)
        n = camera.resolution
        if zr_map.shape != (n, n) or np.shape(depth.mask) != (n, n):
            raise NirspiError(f"fusion: depth map {zr_map.shape} does not match the camera ({n}x{n})")
        valid = np.asarray(depth.mask, dtype=bool) & np.isfinite(zr_map)
        bad = int((np.asarray(depth.mask, dtype=bool) & ~np.isfinite(zr_map)).sum())
        if bad:
            warnings.warn(f"fusion: {bad} masked SFS pixels are not finite; dropped", stacklevel=3)
        if not valid.any():
            raise NirspiError("fusion: the SFS depth map has no valid pixel (empty mask)")
        spikes = 0
        if self.despike_k is not None:
            unit = 1.0 if not depth.metric else float(np.median(zr_map[valid])) / camera.focal_px
            kept = despike(zr_map, valid, self.despike_k, unit)
            spikes, valid = int(valid.sum() - kept.sum()), kept
        used, zr, z, sig, reasons = self._anchor_values(zr_map, valid, itof, camera)
        prior_m = None if self.prior_distance_mm is None else self.prior_distance_mm * 1e-3
        prior_sig = None if prior_m is None else self.prior_distance_rel * prior_m
        wrap = float((itof.info or {}).get("ambiguity_range_m", np.inf))
        useless = sig * np.sqrt(12.0) >= wrap  # a wrapped phase this noisy is uniform over the range
        for k in np.flatnonzero(used & useless):
            used[k] = False
            reasons[k] = (
                f"uninformative: sigma {sig[k]:.3g} m >= the iToF's ambiguity range / sqrt(12) = "
                f"{wrap / np.sqrt(12.0):.3g} m (its wrapped phase is then about uniform over the range)"
            )
            warnings.warn(f"fusion: iToF spot {k} not used: {reasons[k]}", stacklevel=3)
        if not used.any() and prior_m is not None:
            warnings.warn(
                "fusion: no usable iToF anchor; the depth is placed by the working-distance prior alone "
                f"(fusion.prior_distance_mm={self.prior_distance_mm:g}) at the geometric scale",
                stacklevel=3,
            )
        elif not used.any():
            why = "; ".join(f"spot {k}: {r}" for k, r in enumerate(reasons)) or "the iToF sample has no spot"
            raise NirspiError(f"fusion: no valid iToF anchor on the SFS depth map ({why}); cannot make it metric")
        idx = np.flatnonzero(used)
        zr_u, z_u = zr[used], z[used]
        # the reference of the placement c and of the geometric scale c/f: the anchors' mean SFS
        # depth (one relative unit is a pixel pitch at the anchors' depth, as the old s0 = Z̄/f);
        # the map's median without anchors. Fixed for every fit below (leave-one-out included).
        ref_zr = float(np.mean(zr_u)) if len(zr_u) else float(np.median(zr_map[valid]))
        focal = None if depth.metric else float(camera.focal_px)

        def scale_prior(count: int) -> float | None:  # one anchor cannot fit a scale: use the prior
            return self.scale_prior_rel if count >= 2 else (self.scale_prior_rel or 0.2)

        def fit_on(sig_all: np.ndarray) -> Callable[[np.ndarray], AnchorFit]:
            def fit(ix: np.ndarray) -> AnchorFit:
                return fit_anchors(
                    zr_u[ix], z_u[ix], sig_all[ix], ref_zr, focal, scale_prior(len(ix)), prior_m, prior_sig
                )

            return fit

        # the SFS noise in metres needs the scale: first the geometric one at the anchors' median
        # depth (robust to a wild anchor; the prior's without anchors), then the fitted one
        noise_rel = depth_noise(zr_map, valid)  # SFS noise, depth units
        c_guess = float(np.median(z_u)) if len(z_u) else float(prior_m or 1.0)
        scale = c_guess / focal if focal is not None else 1.0
        for _ in range(2):
            sfs_sigma = scale * noise_rel  # metres
            eff_all = np.sqrt(sig[used] ** 2 + sfs_sigma**2)
            relief = scale * float(np.ptp(zr_map[valid]))  # metres: the SFS map's own depth extent
            keep, rejected, cur = consistent_anchors(
                zr_u, z_u, eff_all, self.anchor_alpha, fit_on(eff_all), ref_zr, focal, relief
            )
            scale = cur.scale
        for j, why in rejected.items():
            used[idx[j]] = False
            reasons[idx[j]] = why
            warnings.warn(f"fusion: iToF spot {idx[j]} not used: {why}", stacklevel=3)
        eff_sig = eff_all[keep]
        s, t = cur.scale, cur.offset_m
        z_m = s * zr_map + t
        pts = np.asarray(itof.points_m, dtype=np.float64).reshape(-1, 3)
        delta = np.zeros(len(pts))
        gains = np.zeros(len(pts))
        quality = self._quality(
            cur, len(keep), len(rejected), scale_prior(len(keep)) is not None, prior_m, prior_sig, eff_sig
        )
        # local offsets only where the anchors place the depth (not a prior) and are not flagged
        placed = float(quality.get("anchor_share", 1.0)) >= 0.5 and not quality["worse_than_sfs"]
        if self.local_offsets and placed and used.sum() >= self.min_anchors_local:
            resid = z[used] - (s * zr[used] + t)
            var = eff_sig**2
            # positive-part shrinkage: only the disagreement beyond the combined noise is applied
            g = np.clip(1.0 - var / np.maximum(resid**2, 1e-300), 0.0, 1.0)
            delta[used], gains[used] = g * resid, g
            row_a, col_a = project_px(pts[used], camera)
            rows, cols = np.mgrid[0:n, 0:n]
            w = anchor_weights(rows, cols, np.stack([row_a, col_a], axis=1), self.blend_px)
            z_m = z_m + np.sum(w * delta[used], axis=-1)  # not `@`: BLAS-free bits
        valid &= np.isfinite(z_m) & (z_m > 0)
        if not valid.any():
            raise NirspiError("fusion: the metric depth is not positive anywhere (bad anchors?)")
        fit = {
            "scale": s,
            "scale_prior": cur.scale_ref,
            "offset_m": t,
            "placement_m": cur.placement_m,
            "placement_sigma_m": cur.placement_sigma_m,
            "region_offsets_m": [float(v) for v in delta],
            "offset_gains": [float(v) for v in gains],
            "anchors_used": int(used.sum()),
            "anchors_rejected": {str(k): r for k, r in enumerate(reasons) if r},
            "sfs_noise_m": float(sfs_sigma),
            "spikes_removed": spikes,
            **quality,
        }
        return np.where(valid, z_m, np.inf), valid, fit

    def _quality(
        self,
        cur: AnchorFit,
        n_kept: int,
        n_inconsistent: int,
        scale_prior: bool,
        prior_m: float | None,
        prior_sig: float | None,
        eff_sig: np.ndarray,
    ) -> dict:
        """The fit's χ² test, the anchors' share of the placement and the ``worse_than_sfs``
        flag for the record; warns about a flag or a placement that the anchors hardly inform.

        Flagged (with a placement prior) when :func:`worse_than_prior` says so, or when the χ²
        test rejected at least as many anchors as it kept: the anchors then disagree among
        themselves and nothing but their count decides which are right, so their placement is
        not expected to beat the prior's (a rule, not a computed expectation)."""
        from scipy.stats import chi2 as chi2_dist  # start-up: loads scipy.stats

        out: dict = {"chi2": cur.chi2, "chi2_dof": cur.dof}
        if cur.dof >= 1:
            out["chi2_p"] = float(chi2_dist.sf(cur.chi2, cur.dof))
        why = worse_than_prior(cur, prior_sig, n_kept, scale_prior)
        if why is None and prior_sig is not None and n_inconsistent and n_inconsistent >= n_kept:
            why = (
                f"the chi2 test rejected {n_inconsistent} of {n_kept + n_inconsistent} anchors as inconsistent: "
                "the anchors disagree among themselves, so the kept ones are not expected to place the depth "
                "better than the working-distance prior"
            )
        out["worse_than_sfs"] = why is not None
        if prior_m is not None and prior_sig is not None:
            share = float(np.clip(1.0 - (cur.placement_sigma_m / prior_sig) ** 2, 0.0, 1.0))
            out.update(prior_distance_m=prior_m, anchor_share=share)
            if share < 0.5 and why is None and n_kept:
                warnings.warn(
                    f"fusion: the {n_kept} iToF anchor(s) (sigma {float(eff_sig.min()):.3g} m at best) carry "
                    f"{100 * share:.0f} % of the depth placement; the rest is the working-distance prior "
                    f"(fusion.prior_distance_mm={self.prior_distance_mm:g}, +- {100 * self.prior_distance_rel:g} %)",
                    stacklevel=4,
                )
        if why is not None:
            out["worse_than_sfs_reason"] = why
            warnings.warn(f"fusion: fused depth flagged worse than SFS alone: {why}", stacklevel=4)
        return out

    def voxel_size_m(self, z_m: np.ndarray, valid: np.ndarray, camera: Camera) -> float:
        """The merging voxel, metres: ``voxel_mm``, or ``voxel_px`` pixel pitches at the object's
        median depth capped at ``1/min_voxels_across`` of its smaller image extent (metres)."""
        if self.voxel_mm is not None:
            return self.voxel_mm * 1e-3
        zmed = float(np.median(z_m[valid]))
        pitch = zmed / camera.focal_px
        rows, cols = np.nonzero(valid)
        extent_px = min(rows.max() - rows.min(), cols.max() - cols.min()) + 1
        return float(min(self.voxel_px * pitch, extent_px * pitch / self.min_voxels_across))

    def _diffuse(self, cloud: np.ndarray, noise_m: float) -> tuple[np.ndarray, float]:
        """One implicit heat step on the cloud (``range`` or ``xyz``), its ``t`` chosen by the
        discrepancy principle (Morozov) when ``adaptive_step``: the largest ``t ≤ time_step``
        whose 95th-percentile point movement stays within ``1.96 × noise_m`` (the 95th
        percentile of Gaussian noise of standard deviation ``noise_m``). The movement grows
        about linearly with small ``t``; two secant steps find it. Returns the cloud and ``t``."""
        step = float(self.time_step)
        if step == 0 or len(cloud) < 3:
            return cloud, 0.0
        r = np.linalg.norm(cloud, axis=1)
        graph = _heat_graph(cloud, self.knn)  # the same for every trial t (what heat_diffusion builds)

        def apply(t: float) -> tuple[np.ndarray, float]:
            if self.diffuse == "range":
                r2 = _heat_step(r, *graph, t)
                return cloud / r[:, None] * r2[:, None], float(np.percentile(np.abs(r2 - r), 95))
            c2 = _heat_step(cloud, *graph, t)
            return c2, float(np.percentile(np.linalg.norm(c2 - cloud, axis=1), 95))

        out, moved = apply(step)
        target = 1.96 * noise_m
        for _ in range(2):
            if not self.adaptive_step or moved <= 1.05 * target:
                break
            step *= target / moved if moved > 0 else 0.0
            if step <= 0:
                return cloud, 0.0
            out, moved = apply(step)
        return out, step

    # -- the whole fusion ----------------------------------------------------------------------
    def fuse(self, depth: DepthMap, itof: ItofSample | None, camera: Camera) -> PointCloud:
        """Fuse the SFS ``depth`` with the iToF points into a metric point cloud (metres)."""
        if itof is None:
            raise ConfigError("itof", None, "an itof stage (fusion=itof anchors SFS depth on the iToF points)")
        z_m, valid, fit = self.metric_depth(depth, itof, camera)
        n = camera.resolution
        xyz = back_project(np.where(valid, z_m, 0.0), camera).reshape(-1, 3)
        faces = grid_triangles(valid)
        if len(faces):
            tri = xyz[faces]
            edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(axis=1)
            faces = faces[edges <= self.max_edge_factor * np.median(edges)]
        if len(faces) == 0:
            raise NirspiError("fusion: no triangle between valid SFS pixels (mask too sparse)")
        # V0 of each triangle (Alg. A4): the vertex nearest the iToF point of its anchor region
        pts = np.asarray(itof.points_m, dtype=np.float64).reshape(-1, 3)
        ok = np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)
        fr, fc = np.divmod(faces[:, 0], n)
        if ok.any():
            row_a, col_a = project_px(pts[ok], camera)
            region = np.argmin(np.hypot(fr[:, None] - row_a, fc[:, None] - col_a), axis=1)
            ref = pts[ok][region]
        else:
            ref = xyz[faces[:, 0]]
        dense = semi_even_points(xyz[faces], ref, self.d_pitch_mm * 1e-3, self.min_angle_deg)  # Alg. A4
        verts = xyz[np.unique(faces)]
        voxel = self.voxel_size_m(z_m, valid, camera)
        merged = voxel_merge(np.concatenate([verts, dense]), voxel)
        if len(merged) < max(16, 0.1 * len(verts)):
            warnings.warn(
                f"fusion: the {voxel * 1e3:.3g} mm voxel merged {len(verts) + len(dense)} points into "
                f"{len(merged)} ({len(verts)} pixels); set fusion.voxel_mm smaller (or null: automatic)",
                stacklevel=2,
            )
        keep = (
            remove_outliers(merged, self.knn, self.outlier_std)
            if self.outlier_std is not None
            else np.ones(len(merged), dtype=bool)
        )
        cloud = merged[keep]
        cloud, step = self._diffuse(cloud, float(fit["sfs_noise_m"]))
        if not np.all(np.isfinite(cloud)):
            raise NirspiError("fusion: non-finite points after filtering")
        normals = pca_normals(cloud, self.knn)
        info = {
            **fit,
            "pixels": int(valid.sum()),
            "triangles": int(len(faces)),
            "points_a4": int(len(dense)),
            "points_voxel": int(len(merged)),
            "outliers_removed": int((~keep).sum()),
            "points": int(len(cloud)),
            "voxel_m": voxel,
            "time_step": step,
        }
        return PointCloud(
            points_m=cloud,
            normals=normals,
            depth_scale=float(fit["scale"]),
            depth_offset_m=float(fit["offset_m"]),
            info=info,
        )
