"""The anchors' fit of the fusion ``itof`` (Alg. A3, step 1 of :mod:`nirspi_pipe.mesh.fusion`).

The relative SFS depth is made metric by a weighted fit of a scale and an offset to the iToF
anchors (:func:`fit_anchors`, Levenberg-Marquardt over a log scale ratio and the placement, with
priors), after a leave-one-out outlier test (:func:`consistent_anchors`); :func:`worse_than_prior`
flags a placement the fit itself expects to be worse than the working-distance prior's;
:func:`depth_noise` estimates the SFS map's noise that weights the anchors; :func:`anchor_weights`
and :func:`region_weights` blend per-anchor offsets over the image.

The fit uses elementwise IEEE operations and sums only, no BLAS or LAPACK (the 2×2 covariance is
inverted in closed form), so that it gives the same bits under every OpenBLAS kernel set
(docs/sweeps.md). Its residuals (a handful: one per anchor and prior) are Python floats summed in
numpy's own order (:func:`np_sum`): the same bits as the numpy arrays it used before, without the
cost of a dozen tiny numpy calls per step (the leave-one-out fits ran about 110 residual
evaluations a job).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from nirspi_pipe.errors import NirspiError

__all__ = [
    "AnchorFit",
    "fit_anchors",
    "consistent_anchors",
    "worse_than_prior",
    "depth_noise",
    "fit_with_shape_error",
    "anchor_weights",
    "region_weights",
]


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
        shape_error_m: ``τ``, the SFS shape error at the anchors that the fit added to every
            anchor's σ (metres; :func:`fit_with_shape_error`; 0 = none).
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
    shape_error_m: float = 0.0

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


def _pairwise_sum(a: Sequence[float], lo: int, n: int) -> float:
    """numpy's pairwise summation of ``a[lo:lo + n]`` (``pairwise_sum`` in numpy's
    ``loops_utils.h``): plain below 8 terms, eight running sums up to 128, halves above."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    if n <= 128:
        r0, r1, r2, r3, r4, r5, r6, r7 = a[lo : lo + 8]
        i = 8
        while i < n - n % 8:
            p = lo + i
            r0, r1, r2, r3 = r0 + a[p], r1 + a[p + 1], r2 + a[p + 2], r3 + a[p + 3]
            r4, r5, r6, r7 = r4 + a[p + 4], r5 + a[p + 5], r6 + a[p + 6], r7 + a[p + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        for q in range(lo + i, lo + n):
            res += a[q]
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise_sum(a, lo, n2) + _pairwise_sum(a, lo + n2, n - n2)


def np_sum(a: Sequence[float]) -> float:
    """``float(np.sum(np.array(a, dtype=np.float64)))`` for a sequence of Python floats, with the
    same bits (numpy's reduction starts from 0.0 and adds the pairwise sum;
    tests/test_mesh_speed.py compares them on random lengths and magnitudes)."""
    return 0.0 + _pairwise_sum(a, 0, len(a))


def _dots(u: Sequence[float], v: Sequence[float]) -> float:
    """``float(np.sum(u * v))`` of two equal-length float sequences, same bits (:func:`np_sum`;
    below 8 terms, the fit's case, its plain loop written in place)."""
    if len(u) < 8:
        res = -0.0
        for x, y in zip(u, v):
            res += x * y
        return 0.0 + res
    return np_sum([x * y for x, y in zip(u, v)])


_Residuals = tuple[list[float], list[float], list[float]]


def _levenberg_marquardt(
    fun: Callable[[tuple[float, float]], _Residuals],
    x0: tuple[float, float],
    u_bound: float,
    v_max: float,
    max_iter: int = 200,
) -> tuple[float, float]:
    """Minimise ``Σ r²`` over two parameters ``(u, v)``, ``|u| ≤ u_bound``, ``v ≤ v_max``, by
    Levenberg–Marquardt with Marquardt's diagonal scaling (Nocedal & Wright, *Numerical
    Optimization*, 2nd ed., §10.3), steps projected onto the bounds. ``fun`` returns the
    residuals and their derivatives in ``u`` and ``v``.

    Written out with elementwise IEEE operations and numpy-ordered sums only (:func:`np_sum`), so
    that the fit gives the same bits under every OpenBLAS/LAPACK kernel set
    (``scipy.optimize.least_squares`` did not: its last bits moved the fused cloud of one CI
    job, docs/sweeps.md)."""

    def clip(u: float, v: float) -> tuple[float, float]:
        return min(max(u, -u_bound), u_bound), min(v, v_max)

    x = clip(*x0)
    r, ju, jv = fun(x)
    cost = _dots(r, r)
    lam = 1e-3
    for _ in range(max_iter):
        a, b, d = _dots(ju, ju), _dots(ju, jv), _dots(jv, jv)
        gu, gv = _dots(ju, r), _dots(jv, r)
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
            cost_new = _dots(r_new, r_new)
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
    sp = _scale_prior(zr, k, scale_prior_rel, has_prior)
    b = zr - ref_zr
    rel = focal_px is not None
    f_px = float(focal_px) if focal_px is not None else 1.0
    prior = (float(prior_m), float(prior_sigma_m)) if has_prior else None  # type: ignore[arg-type]
    residuals = _anchor_residuals(b, z, sig, f_px if rel else None, sp, prior)
    c0 = _start_placement(b, z, sig, f_px if rel else None, prior)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        x = _levenberg_marquardt(residuals, (0.0, math.log(c0)), _LOG_RATIO_BOUND, math.log(1e12))
        res_l, ju, jv = residuals(x)
        cov = _inv_sym2(_dots(ju, ju), _dots(ju, jv), _dots(jv, jv))
    res = np.array(res_l, dtype=np.float64)
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


def _scale_prior(zr: np.ndarray, k: int, scale_prior_rel: float | None, has_prior: bool) -> float | None:
    """The scale prior the fit uses (0.2 without anchors, as with one), or None; fails when
    there is nothing to fit or the anchors cannot determine the scale without a prior."""
    if k == 0 and not has_prior:
        raise NirspiError("fusion: no valid iToF anchor on the SFS depth map; cannot make it metric")
    if k == 0 and scale_prior_rel is None:
        scale_prior_rel = 0.2  # no anchor: the scale is the geometric one, as with one anchor
    if scale_prior_rel is None and (k < 2 or float(np.ptp(zr)) <= 0):
        raise NirspiError(
            f"fusion: the {k} iToF anchor(s) cannot determine the depth scale and offset "
            "(anchors at equal SFS depth?); set fusion.scale_prior_rel"
        )
    return None if scale_prior_rel is None else float(scale_prior_rel)


def _anchor_residuals(
    b: np.ndarray,
    z: np.ndarray,
    sig: np.ndarray,
    focal: float | None,
    sp: float | None,
    prior: tuple[float, float] | None,
) -> Callable[[tuple[float, float]], _Residuals]:
    """The fit's residuals and their derivatives in ``u`` and ``ln c`` (analytic), as a function
    of ``(u, ln c)``; ``focal`` None: metric SFS depth. Lists of Python floats: the anchors'
    terms, then the scale prior's and the placement prior's where given (the same IEEE
    operations, in the same order, as numpy's elementwise ``(c + s·b − z)/σ`` and so on).

    Raises:
        NirspiError: an anchor with ``σ = 0`` (its residual is not finite: the fit cannot converge
            to finite values, as numpy's division by zero made it fail before).
    """
    rel = focal is not None
    f_px = focal if focal is not None else 1.0
    has_prior = prior is not None
    pm, ps = prior if prior is not None else (0.0, 1.0)
    terms = list(zip(b.tolist(), z.tolist(), sig.tolist()))
    if any(si == 0.0 for _, _, si in terms):
        raise NirspiError("fusion: the anchors' fit of the depth scale and offset did not converge to finite values")

    def residuals(x: tuple[float, float]) -> _Residuals:
        """Residuals and their derivatives in ``u`` and ``ln c`` (analytic)."""
        eu, c = math.exp(x[0]), math.exp(x[1])
        s = eu * (c / f_px if rel else 1.0)
        r = [(c + s * bi - zi) / si for bi, zi, si in terms]
        du = [s * bi / si for bi, _, si in terms]
        dv = [(c + s * bi) / si for bi, _, si in terms] if rel else [(c + 0.0 * bi) / si for bi, _, si in terms]
        if sp is not None:  # ratio e^u ~ N(1, rel), > 0
            r.append(math.expm1(x[0]) / sp)
            du.append(eu / sp)
            dv.append(0.0)
        if has_prior:
            r.append((c - pm) / ps)
            du.append(0.0)
            dv.append(c / ps)
        return r, du, dv

    return residuals


def _start_placement(
    b: np.ndarray, z: np.ndarray, sig: np.ndarray, focal: float | None, prior: tuple[float, float] | None
) -> float:
    """The fit's start: the weighted least-squares placement at ``u = 0`` (closed form)."""
    k = len(z)
    rel = focal is not None
    f_px = focal if focal is not None else 1.0
    w = 1.0 / sig**2
    a = 1.0 + b / f_px if rel else np.ones(k)
    shift = np.zeros(k) if rel else b
    num = float(np.sum(w * a * (z - shift)))
    den = float(np.sum(w * a * a))
    if prior is not None:
        pm, ps = prior
        num += pm / ps**2
        den += 1.0 / ps**2
    c0 = num / den if den > 0 and np.isfinite(num / den) else float(np.median(z))
    return max(c0, 1e-9 * max(float(np.max(np.abs(z), initial=0.0)), 1e-3))


@lru_cache(maxsize=64)
def _chi2_limit(alpha: float, k: int) -> float:
    """The χ²₁ quantile at ``1 − alpha/k`` (:func:`consistent_anchors`' Bonferroni bound),
    computed once per ``(alpha, k)`` in a process: scipy.stats' quantile cost more than the
    anchors' fits it decides on."""
    from scipy.stats import chi2 as chi2_dist  # start-up: loads scipy.stats (only for the test)

    return float(chi2_dist.ppf(1.0 - alpha / k, 1))


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
        limit = _chi2_limit(alpha, len(keep))
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


@lru_cache(maxsize=64)
def _chi2_quantile(alpha: float, dof: int) -> float:
    """The χ² quantile at ``1 − alpha`` on ``dof`` degrees of freedom (:func:`fit_with_shape_error`'s
    test), computed once per ``(alpha, dof)`` in a process."""
    from scipy.stats import chi2 as chi2_dist  # start-up: loads scipy.stats (only for the test)

    return float(chi2_dist.ppf(1.0 - alpha, dof))


#: Relative precision of :func:`fit_with_shape_error`'s ``τ`` (Brent's method in ``ln τ``; assumed:
#: 0.1 % of an SFS shape error is far below anything the fit's weights resolve).
_TAU_REL_TOL = 1e-3


def fit_with_shape_error(
    fit_sigma: Callable[[np.ndarray], AnchorFit],
    sigma: np.ndarray,
    alpha: float,
    misfit: Callable[[np.ndarray], AnchorFit] | None = None,
) -> AnchorFit:
    """The anchors' fit with the SFS map's shape error ``τ`` added to every anchor's σ where the
    anchors need it: ``fit_sigma(sqrt(σ² + τ²))``.

    The fit ``z_k ≈ s·zr_k + t`` assumes the SFS shape is right up to scale and offset; it is not
    (a few mm of relative-depth error at the spots, which the local offsets then absorb), and the
    anchors' σ alone hides that once the anchors are precise: with ``σ`` ≈ 10 µm (a noiseless
    iToF) the fit follows four spots' shape error wherever it leads, overrules the scale prior
    and drives the scale to its bound. So ``τ > 0`` only when two χ² tests at level ``alpha``
    both fail: the fit's own (anchors and priors, on its ``dof``), and the anchors' against the
    best *positive* scale and offset for them alone, ``misfit`` (the caller: the same fit without
    the scale prior; None = the fit itself). The second keeps ``τ = 0`` where the anchors agree
    with an SFS depth of another scale than the prior's (SFS's scale is off, not its shape: the
    anchors are then right to move it). ``τ`` is then the Paule–Mandel estimate on ``misfit``:
    the ``τ`` at which its χ² equals its degrees of freedom (Paule & Mandel, *Consensus values and
    weighting factors*, J. Res. NBS 87, 377–385, 1982; the between-study variance of a
    random-effects meta-analysis; the tests are Cochran's Q). Otherwise the result is
    ``fit_sigma(σ)`` itself.

    The χ² of the refit falls monotonically with ``τ`` (each weight does), so ``τ`` is found by
    bracketing (×4 steps) and Brent's method in ``ln τ`` to ``_TAU_REL_TOL``. ``fit_sigma`` raises
    (:class:`NirspiError`) as :func:`fit_anchors` does; where ``misfit`` raises (one anchor, or
    all at one SFS depth: no scale of their own), ``τ = 0``.
    """
    from scipy.optimize import brentq  # start-up: loads scipy.optimize (only when the test fires)

    sig = np.asarray(sigma, dtype=np.float64)
    cur = fit_sigma(sig)
    if cur.dof < 1 or not cur.chi2 > _chi2_quantile(alpha, cur.dof):
        return cur
    judge = fit_sigma if misfit is None else misfit
    try:
        base = cur if misfit is None else misfit(sig)
    except NirspiError:
        return cur
    if base.dof < 1 or not base.chi2 > _chi2_quantile(alpha, base.dof):
        return cur
    target = float(base.dof)
    fits: dict[float, AnchorFit] = {}

    def excess(log_tau: float) -> float:
        """``ln(χ²(τ)/dof)`` of ``judge``: positive below the root, negative above it."""
        tau = math.exp(log_tau)
        fits[log_tau] = replace(judge(np.sqrt(sig * sig + tau * tau)), shape_error_m=tau)
        return math.log(max(fits[log_tau].chi2, 1e-300) / target)

    # the start: the residual that would give this chi2 (chi2 ~ k r²/σ²), then bracket by x4 steps
    lo = hi = math.log(max(float(np.max(sig, initial=0.0)), 1e-12) * math.sqrt(base.chi2 / target))
    step = math.log(4.0)
    root = None
    if excess(hi) > 0:
        for _ in range(64):  # 4^64: far beyond any chi2 the priors leave
            lo, hi = hi, hi + step
            if excess(hi) <= 0:
                break
        else:
            root = hi  # not bracketed: the largest τ tried
    else:
        for _ in range(16):  # 4^-16 of the start: τ that small changes no weight
            hi, lo = lo, lo - step
            if excess(lo) > 0:
                break
        else:
            root = lo  # the smallest τ tried already suffices
    if root is None:
        root = float(brentq(excess, lo, hi, xtol=_TAU_REL_TOL, rtol=4 * np.finfo(float).eps))
        # the side of the root where χ² ≤ dof (brentq's answer is within xtol of it, either side)
        for side in (root, min(root + 2.0 * _TAU_REL_TOL, hi), hi):
            if excess(side) <= 0:
                root = side
                break
    if misfit is None:
        return fits[root]
    tau = fits[root].shape_error_m
    return replace(fit_sigma(np.sqrt(sig * sig + tau * tau)), shape_error_m=tau)


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
