"""Fusion ``itof``: SFS depth + four iToF points → a metric, filtered point cloud (Algs. A3/A4).

Steps (see docs/mesh.md for the derivations and the departures from the paper):

0. **Despiking.** SFS pixels that stand out of their 3×3 median by more than ``despike_k``
   robust standard deviations are dropped (SFS outliers; the paper removes them with its filter).
1. **Anchors and metric scaling (Alg. A3).** The relative SFS depth ``z_r`` becomes metric depth
   ``Z = s·z_r + t + Σ_k w_k(pixel)·δ_k``. The global scale and offset are fitted to the valid
   iToF anchors (:func:`fit_anchors`) as a placement ``c`` (the metric depth at the anchors'
   mean SFS depth) and a log scale ratio ``u``, ``s = e^u·c/f`` (one relative unit is a pixel
   pitch at the anchors' depth), so the scale is positive by construction; weighted least squares with
   weights ``1/(σ_k² + σ_SFS² + τ²)`` (``σ_SFS`` the SFS noise estimated from the map,
   :func:`depth_noise`; ``τ`` the SFS shape error at the spots, with ``shape_error`` only: 0
   unless both the fit's χ² and that of the anchors' own best positive scale and offset exceed
   their ``1 − anchor_alpha`` quantiles, then the latter's Paule–Mandel root χ² = dof,
   :func:`fit_with_shape_error`: precise anchors no longer follow SFS's few mm of shape error
   into a collapsed scale), a prior ``e^u ~ N(1, scale_prior_rel)`` on the scale and a Gaussian prior on
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

This module holds the stage, :class:`ItofFusion`, which runs the steps: the anchors' fit of step 1
is in :mod:`nirspi_pipe.mesh.anchors`, the array work of steps 0 and 2-6 in
:mod:`nirspi_pipe.mesh.pointcloud`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.mesh.anchors import (
    AnchorFit,
    anchor_weights,
    consistent_anchors,
    depth_noise,
    fit_anchors,
    fit_with_shape_error,
    worse_than_prior,
)
from nirspi_pipe.mesh.pointcloud import (
    back_project,
    despike,
    grid_triangles,
    heat_graph,
    heat_step,
    pca_normals,
    project_px,
    remove_outliers,
    semi_even_points,
    voxel_merge,
)
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.types import Camera, DepthMap, ItofSample, PointCloud

__all__ = ["ItofFusion"]


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
            noise of the others' prediction is rejected, :func:`consistent_anchors`) and, with
            ``shape_error``, of the test that adds the SFS shape error to the anchors' σ
            (:func:`fit_with_shape_error`); null = neither.
        shape_error: add the SFS shape error ``τ`` to the anchors' σ when they disagree with the
            SFS shape beyond it (step 1 above; ``+fusion.shape_error=true``); off by default.
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

    d_pitch_mm: Annotated[float, Range(0.0, None, "a pitch in mm", lo_open=True)] = 5.0
    voxel_mm: Annotated[float | None, Range(0.0, None, "a voxel size in mm", lo_open=True, note="null: automatic")] = (
        None
    )
    voxel_px: Annotated[float, Range(0.0, None, "pixel pitches", lo_open=True)] = 2.0
    min_voxels_across: Annotated[int, Range(2, 4096, "an integer", integer=True)] = 16
    min_angle_deg: Annotated[float, Range(0.0, 90.0, "degrees", lo_open=True, hi_open=True)] = 1.0
    scale_prior_rel: Annotated[float | None, Range(0.0, None, "a relative tolerance", lo_open=True)] = 0.2
    prior_distance_mm: Annotated[float | None, Range(0.0, None, "a distance in mm", lo_open=True)] = None
    prior_distance_rel: Annotated[float, Range(0.0, None, "a relative tolerance", lo_open=True)] = 0.25
    anchor_alpha: Annotated[
        float | None, Range(0.0, 1.0, "a test level", lo_open=True, hi_open=True, note="null: no test")
    ] = 0.01
    local_offsets: Annotated[bool, OneOf((True, False), "true or false")] = True
    min_anchors_local: Annotated[int, Range(1, 64, "an integer", integer=True)] = 3
    blend_px: Annotated[float, Range(0.0, None, "pixels")] = 8.0
    anchor_radius_px: Annotated[float, Range(0.0, None, "pixels")] = 2.0
    despike_k: Annotated[float | None, Range(0.0, None, "standard deviations", lo_open=True)] = 4.0
    max_edge_factor: Annotated[float, Range(1.0, None, "a factor", lo_open=True)] = 4.0
    knn: Annotated[int, Range(3, 64, "an integer", integer=True)] = 8
    outlier_std: Annotated[float | None, Range(0.0, None, "standard deviations", lo_open=True)] = 2.5
    time_step: Annotated[float, Range(0.0, None, "a dimensionless step")] = 8.0
    adaptive_step: Annotated[bool, OneOf((True, False), "true or false")] = True
    diffuse: Annotated[str, OneOf(("range", "xyz"))] = "range"
    # Not in the generated config schema (never a key of fusion=itof; +fusion.shape_error=true sets
    # it): the configs and job keys of fusion runs stay as they were. Off by default because it
    # changes the paper's Table 3/4 jobs where the anchors disagree with the SFS shape (docs/mesh.md,
    # "Cleaner anchors"), and the claims made of those tables were derived without it.
    shape_error: Annotated[bool, OneOf((True, False), "true or false")] = field(
        default=False, metadata={"config": False}
    )

    def __post_init__(self) -> None:
        check_ranges(self)

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

    def _valid_sfs(self, depth: DepthMap, camera: Camera) -> tuple[np.ndarray, np.ndarray, int]:
        """Alg. A3's input: the SFS map as floats, its valid pixels (masked, finite, not spikes)
        and the count of spikes removed; a map of the wrong shape or without a valid pixel fails."""
        zr_map = np.asarray(depth.depth_m, dtype=np.float64)
        n = camera.resolution
        if zr_map.shape != (n, n) or np.shape(depth.mask) != (n, n):
            raise NirspiError(f"fusion: depth map {zr_map.shape} does not match the camera ({n}x{n})")
        valid = np.asarray(depth.mask, dtype=bool) & np.isfinite(zr_map)
        bad = int((np.asarray(depth.mask, dtype=bool) & ~np.isfinite(zr_map)).sum())
        if bad:
            warnings.warn(f"fusion: {bad} masked SFS pixels are not finite; dropped", stacklevel=4)
        if not valid.any():
            raise NirspiError("fusion: the SFS depth map has no valid pixel (empty mask)")
        spikes = 0
        if self.despike_k is not None:
            unit = 1.0 if not depth.metric else float(np.median(zr_map[valid])) / camera.focal_px
            kept = despike(zr_map, valid, self.despike_k, unit)
            spikes, valid = int(valid.sum() - kept.sum()), kept
        return zr_map, valid, spikes

    def _drop_uninformative(
        self, used: np.ndarray, sig: np.ndarray, reasons: list[str], itof: ItofSample, prior_m: float | None
    ) -> None:
        """Marks unused (in place, warned, reason listed) the anchors whose σ makes their wrapped
        phase about uniform over the ambiguity range; fails when no anchor and no prior are left."""
        wrap = float((itof.info or {}).get("ambiguity_range_m", np.inf))
        useless = sig * np.sqrt(12.0) >= wrap  # a wrapped phase this noisy is uniform over the range
        for k in np.flatnonzero(used & useless):
            used[k] = False
            reasons[k] = (
                f"uninformative: sigma {sig[k]:.3g} m >= the iToF's ambiguity range / sqrt(12) = "
                f"{wrap / np.sqrt(12.0):.3g} m (its wrapped phase is then about uniform over the range)"
            )
            warnings.warn(f"fusion: iToF spot {k} not used: {reasons[k]}", stacklevel=4)
        if not used.any() and prior_m is not None:
            warnings.warn(
                "fusion: no usable iToF anchor; the depth is placed by the working-distance prior alone "
                f"(fusion.prior_distance_mm={self.prior_distance_mm:g}) at the geometric scale",
                stacklevel=4,
            )
        elif not used.any():
            why = "; ".join(f"spot {k}: {r}" for k, r in enumerate(reasons)) or "the iToF sample has no spot"
            raise NirspiError(f"fusion: no valid iToF anchor on the SFS depth map ({why}); cannot make it metric")

    def _scale_prior(self, count: int) -> float | None:
        """The scale prior of a fit on ``count`` anchors: one anchor cannot fit a scale, so it gets one."""
        return self.scale_prior_rel if count >= 2 else (self.scale_prior_rel or 0.2)

    def _consistent_fit(
        self,
        zr_map: np.ndarray,
        valid: np.ndarray,
        zr_u: np.ndarray,
        z_u: np.ndarray,
        sig_u: np.ndarray,
        focal: float | None,
        prior_m: float | None,
        prior_sig: float | None,
    ) -> tuple[np.ndarray, dict[int, str], AnchorFit, np.ndarray, float]:
        """The global fit on the consistent anchors: ``(keep, rejected, fit, eff_sigma, sfs_sigma)``,
        ``eff_sigma`` each used anchor's σ with the SFS noise, ``sfs_sigma`` that noise in metres."""
        # the reference of the placement c and of the geometric scale c/f: the anchors' mean SFS
        # depth (one relative unit is a pixel pitch at the anchors' depth, as the old s0 = Z̄/f);
        # the map's median without anchors. Fixed for every fit below (leave-one-out included).
        ref_zr = float(np.mean(zr_u)) if len(zr_u) else float(np.median(zr_map[valid]))

        def fit_on(sig_all: np.ndarray) -> Callable[[np.ndarray], AnchorFit]:
            def fit(ix: np.ndarray) -> AnchorFit:
                def with_sigma(sig: np.ndarray) -> AnchorFit:
                    return fit_anchors(
                        zr_u[ix], z_u[ix], sig, ref_zr, focal, self._scale_prior(len(ix)), prior_m, prior_sig
                    )

                def free_scale(sig: np.ndarray) -> AnchorFit:  # the anchors' own scale: no scale prior
                    return fit_anchors(zr_u[ix], z_u[ix], sig, ref_zr, focal, None, prior_m, prior_sig)

                if self.anchor_alpha is None or not self.shape_error:
                    return with_sigma(sig_all[ix])
                # anchors that no positive scale and offset fit within their sigma: SFS's shape error
                return fit_with_shape_error(with_sigma, sig_all[ix], self.anchor_alpha, free_scale)

            return fit

        # the SFS noise in metres needs the scale: first the geometric one at the anchors' median
        # depth (robust to a wild anchor; the prior's without anchors), then the fitted one
        noise_rel = depth_noise(zr_map, valid)  # SFS noise, depth units
        c_guess = float(np.median(z_u)) if len(z_u) else float(prior_m or 1.0)
        scale = c_guess / focal if focal is not None else 1.0
        for _ in range(2):
            sfs_sigma = scale * noise_rel  # metres
            eff_all = np.sqrt(sig_u**2 + sfs_sigma**2)
            relief = scale * float(np.ptp(zr_map[valid]))  # metres: the SFS map's own depth extent
            keep, rejected, cur = consistent_anchors(
                zr_u, z_u, eff_all, self.anchor_alpha, fit_on(eff_all), ref_zr, focal, relief
            )
            scale = cur.scale
        return keep, rejected, cur, eff_all, sfs_sigma

    def _local_offsets(
        self, resid: np.ndarray, var: np.ndarray, pts_used: np.ndarray, camera: Camera
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each used anchor's shrunk offset and gain, and their blend over the image ``(n, n)``."""
        # positive-part shrinkage: only the disagreement beyond the combined noise is applied
        g = np.clip(1.0 - var / np.maximum(resid**2, 1e-300), 0.0, 1.0)
        row_a, col_a = project_px(pts_used, camera)
        n = camera.resolution
        rows, cols = np.mgrid[0:n, 0:n]
        w = anchor_weights(rows, cols, np.stack([row_a, col_a], axis=1), self.blend_px)
        return g * resid, g, np.sum(w * (g * resid), axis=-1)  # not `@`: BLAS-free bits

    def metric_depth(self, depth: DepthMap, itof: ItofSample, camera: Camera) -> tuple[np.ndarray, np.ndarray, dict]:
        """Alg. A3: the metric z-depth map ``(n, n)`` (metres, valid where the returned mask is
        True) and the fit ``{scale, offset_m, region_offsets_m, anchors_used, …}``.

        Degrees of freedom by the number of valid anchors: 1 → the offset (the scale is the prior
        ``Z̄/f``); 2 → offset and scale (with the prior); ≥ ``min_anchors_local`` (3) → also one
        local offset per anchor region, shrunk towards 0 where SFS and iToF agree within their
        combined uncertainty."""
        zr_map, valid, spikes = self._valid_sfs(depth, camera)
        used, zr, z, sig, reasons = self._anchor_values(zr_map, valid, itof, camera)
        prior_m = None if self.prior_distance_mm is None else self.prior_distance_mm * 1e-3
        prior_sig = None if prior_m is None else self.prior_distance_rel * prior_m
        self._drop_uninformative(used, sig, reasons, itof, prior_m)
        idx = np.flatnonzero(used)
        focal = None if depth.metric else float(camera.focal_px)
        keep, rejected, cur, eff_all, sfs_sigma = self._consistent_fit(
            zr_map, valid, zr[used], z[used], sig[used], focal, prior_m, prior_sig
        )
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
            cur, len(keep), len(rejected), self._scale_prior(len(keep)) is not None, prior_m, prior_sig, eff_sig
        )
        # local offsets only where the anchors place the depth (not a prior) and are not flagged
        placed = float(quality.get("anchor_share", 1.0)) >= 0.5 and not quality["worse_than_sfs"]
        if self.local_offsets and placed and used.sum() >= self.min_anchors_local:
            resid = z[used] - (s * zr[used] + t)
            delta[used], gains[used], blend = self._local_offsets(resid, eff_sig**2, pts[used], camera)
            z_m = z_m + blend
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
            "sfs_shape_error_m": float(cur.shape_error_m),
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
        graph = heat_graph(cloud, self.knn)  # the same for every trial t (what heat_diffusion builds)

        def apply(t: float) -> tuple[np.ndarray, float]:
            if self.diffuse == "range":
                r2 = heat_step(r, *graph, t)
                return cloud / r[:, None] * r2[:, None], float(np.percentile(np.abs(r2 - r), 95))
            c2 = heat_step(cloud, *graph, t)
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
