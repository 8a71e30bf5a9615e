"""The point-cloud steps of the fusion ``itof`` (:mod:`nirspi_pipe.mesh.fusion`), on numpy arrays.

Despiking of the SFS map (step 0), back-projection, projection and the pixel grid's triangles
(step 2), Alg. A4's semi-even points (step 3, Eqs. 13-15), voxel merging (step 4), statistical
outlier removal and the implicit heat-diffusion step on the kNN graph (step 5) and PCA normals
(step 6). Units as each function says (metres for points).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.types import Camera

__all__ = [
    "despike",
    "back_project",
    "project_px",
    "grid_triangles",
    "semi_even_points",
    "voxel_merge",
    "remove_outliers",
    "heat_diffusion",
    "heat_graph",
    "heat_step",
    "pca_normals",
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
    return heat_step(values, *heat_graph(points, knn), time_step)


def heat_graph(points: np.ndarray, knn: int) -> tuple[sparse.csr_matrix, np.ndarray]:
    """The kNN heat-kernel graph ``W`` of ``points`` ``(p, 3)`` (metres) and its degrees
    ``D`` ``(p,)`` (dimensionless, floored at 1e-12: an isolated point stays put), which
    :func:`heat_diffusion` uses for any ``t``: :meth:`~nirspi_pipe.mesh.fusion.ItofFusion._diffuse` builds them once for
    its up to three trial steps."""
    w = _knn_graph(points, knn)
    deg = np.asarray(w.sum(axis=1)).ravel()
    return w, np.maximum(deg, 1e-12)


def heat_step(values: np.ndarray, w: sparse.csr_matrix, deg: np.ndarray, time_step: float) -> np.ndarray:
    """Solve ``(D + t(D − W)) x' = D x`` for ``values`` ``(p,)`` or ``(p, c)`` on the graph of
    :func:`heat_graph` (``t = time_step`` > 0, dimensionless); units of ``values`` are kept."""
    p = len(deg)
    a = sparse.csc_matrix(_step_matrix(w, deg, time_step), shape=(p, p))
    rhs = deg[:, None] * np.asarray(values, dtype=np.float64).reshape(p, -1)
    out = spsolve(a, rhs)
    return np.asarray(out).reshape(np.shape(values))


def _step_matrix(w: sparse.csr_matrix, deg: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(data, indices, indptr)`` of ``(1 + t)·D − t·W`` in compressed form, what
    ``((1 + t) * sparse.diags(deg) - t * w).tocsc()`` gives (same values, same stored entries,
    same order; tests/test_mesh_speed.py) without scipy's format conversions (they took a third of
    the heat step on a table3 cloud). ``w`` is the symmetric graph of :func:`heat_graph` in
    canonical CSR form, so the symmetric result's CSR arrays are its CSC arrays. Entries are
    scipy's: ``(1 + t)·deg_i − t·w_ii`` on the diagonal, ``0 − t·w_ij`` off it, exact zeros
    not stored."""
    w = w.tocsr()
    p = len(deg)
    rows = np.repeat(np.arange(p, dtype=w.indices.dtype), np.diff(w.indptr))
    cols = w.indices
    vals = 0.0 - t * w.data
    on_diag = cols == rows
    vals[on_diag] = (1.0 + t) * deg[rows[on_diag]] - t * w.data[on_diag]
    has_diag = np.zeros(p, dtype=bool)
    has_diag[rows[on_diag]] = True
    extra = np.flatnonzero(~has_diag).astype(cols.dtype)
    r_all = np.concatenate([rows, extra])
    c_all = np.concatenate([cols, extra])
    v_all = np.concatenate([vals, (1.0 + t) * deg[extra]])
    # W's entries are sorted by (row, column) and so are the added diagonal ones: a stable sort
    # of the distinct keys merges the two runs (np.lexsort on the int32 indices took 1 ms)
    order = np.argsort(r_all.astype(np.int64) * p + c_all, kind="stable")
    r_all, c_all, v_all = r_all[order], c_all[order], v_all[order]
    stored = v_all != 0
    r_all, c_all, v_all = r_all[stored], c_all[stored], v_all[stored]
    indptr = np.zeros(p + 1, dtype=cols.dtype)
    np.cumsum(np.bincount(r_all, minlength=p), out=indptr[1:])
    return v_all, c_all, indptr


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
