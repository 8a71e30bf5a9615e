"""Metrics ``full``: the 2D image metrics plus the 3D metrics of §7 (Eqs. 16–17, skewness) and
surface distances.

* ``depth_rmse_sfs_mm``: Eq. (16) between the true z-depth and the SFS depth made metric from the
  camera geometry alone, without any iToF information (:func:`geometric_metric_depth`: scale =
  the pixel pitch at the nominal working distance, ``z_nom / focal_px``; the visible surface's
  median depth placed at ``z_nom``) — the paper's RMSE of Alg. A2 as a camera without iToF would
  measure it — over the pixels where SFS, fused and true depth all exist.
* ``depth_rmse_sfs_fit_mm``: the same with the fusion's global scale and offset (``cloud.depth_scale``,
  ``cloud.depth_offset_m``): a baseline that already holds the iToF's global fit.
* ``depth_rmse_sfs_offsetfree_mm``: the geometric baseline with its best constant offset (same
  scale; the offset ``sfs_offset_mm`` = mean of true − baseline depth over the compared pixels,
  the least-squares constant): what is left of the baseline's error once the placement of its
  median at ``z_nom`` is corrected. Since ``RMSE² = (mean error)² + var(error)``, the offset's share
  of the baseline's squared error is ``sfs_offset_mm² / depth_rmse_sfs_mm²``.
* ``depth_rmse_fused_mm``: Eq. (16) between the true z-depth and the fused cloud (output of
  Alg. A3), interpolated on the same pixels (linear over the Delaunay triangulation of the
  points' image positions); ``depth_pixels`` counts the pixels compared. The truth there is the
  pixel's mean depth over its rays that hit (coverage ≥ 0.5), which at a depth jump inside the
  pixel is no surface's depth.
* ``depth_rmse_fused_inner_mm``: the same on the compared pixels *fully inside one surface*
  (:func:`~nirspi_pipe.mesh.truthsurface.inner_pixels`: all their fine samples hit and no
  neighbour pair among them jumps in depth), ``depth_inner_pixels`` of them, a share
  ``depth_inner_share`` (0–1) of ``depth_pixels``; only with the scene model (a fine render).
* ``improvement_pct``: Eq. (17), ``(RMSE_A2 − RMSE_A3) / RMSE_A2 × 100`` with the geometric
  baseline; ``improvement_fit_pct`` the same with the global-fit baseline,
  ``improvement_offsetfree_pct`` with the offset-free baseline. The paper's
  denominator is named ``RMSE_SfS``; SFS *is* Alg. A2, so it is the same number. Positive =
  fusion helped. Omitted (with a warning) when ``RMSE_A2 = 0``.
* On an upscaled run (the device preset; the runner hands over the run's scene model and source,
  :class:`~nirspi_pipe.stages.ScoresWithStages`) the 3D scores are computed
  on the upscaled grid against the scene rendered again there, and the 2D scores are those of
  :class:`~nirspi_pipe.upscale.metrics.UpscaleMetrics`.
* ``skewness_*``: equiangle skewness ``max((θmax − 60°)/120°, (60° − θmin)/60°)`` of the final
  mesh's triangles: mean, 95th percentile and the share in each ANSYS band (excellent < 0.25 ≤
  good < 0.5 ≤ fair < 0.75 ≤ poor < 0.9 ≤ very poor < 1, degenerate = 1);
  ``skewness_sfs_mean`` is the same for the pixel-grid mesh of the metric SFS depth.
* ``chamfer_mm`` / ``hausdorff_mm``: symmetric chamfer (mean of the two mean nearest-neighbour
  distances) and Hausdorff distance between the final mesh and the true visible surface
  (:func:`~nirspi_pipe.mesh.truthsurface.truth_surface`: the scene model ray-cast with one ray per
  sample on a grid 4× finer than the scored one, every hit sample plus the centroids of the faces
  that join samples of one surface; no face bridges a depth jump). The mesh is sampled uniformly at
  ``sample_spacing_mm`` (default: half the true pixel pitch at the scene distance, ~0.55 mm for
  the default sphere at 64²); docs/mesh.md states the metric's own floor. ``surface_distances:
  false`` leaves both out (the paper's experiments, whose tables do not report them).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import matplotlib.tri as mtri
import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.instantiate import build
from nirspi_pipe.mesh.pointcloud import back_project, grid_triangles
from nirspi_pipe.mesh.truthsurface import TruthSurface, inner_pixels, truth_surface
from nirspi_pipe.metrics import ImageMetrics, rmse
from nirspi_pipe.scene.render import render_cached
from nirspi_pipe.stages import Products, RunStages
from nirspi_pipe.types import Camera, DepthMap, PointCloud, Scene

__all__ = [
    "compared_depths",
    "depth_truth",
    "run_depth_truth",
    "geometric_metric_depth",
    "Metrics3D",
    "equiangle_skewness",
    "skewness_summary",
    "improvement_rate",
    "surface_distances",
    "sample_surface",
    "SKEWNESS_BANDS",
]

#: ANSYS equiangle-skewness bands: name, lower bound (inclusive), upper bound (exclusive).
SKEWNESS_BANDS = (
    ("excellent", 0.0, 0.25),
    ("good", 0.25, 0.5),
    ("fair", 0.5, 0.75),
    ("poor", 0.75, 0.9),
    ("very_poor", 0.9, 1.0),
)
_DEGENERATE = 1.0 - 1e-9


def _angles_and_lengths(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(angles (f, 3) degrees, edge lengths (f, 3) metres)`` of triangles: angle ``i`` at vertex
    ``i``, edge ``i`` from vertex ``i`` to vertex ``i + 1``."""
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    if len(v) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    e = [v[:, (i + 1) % 3] - v[:, i] for i in range(3)]  # edges
    lengths = np.stack([np.linalg.norm(x, axis=1) for x in e], axis=1)
    angles = np.zeros((len(v), 3))
    for i in range(3):
        a, b = -e[(i + 2) % 3], e[i]  # the two edges leaving vertex i
        na, nb = lengths[:, (i + 2) % 3], lengths[:, i]
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(na * nb, 1e-300)
        angles[:, i] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angles, lengths


def _skewness_of(angles: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """:func:`equiangle_skewness` from :func:`_angles_and_lengths`."""
    if len(angles) == 0:
        return np.zeros(0)
    skew = np.maximum((angles.max(axis=1) - 60.0) / 120.0, (60.0 - angles.min(axis=1)) / 60.0)
    degenerate = lengths.min(axis=1) <= 1e-12 * np.maximum(lengths.max(axis=1), 1e-300)
    return np.clip(np.where(degenerate, 1.0, skew), 0.0, 1.0)


def equiangle_skewness(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Equiangle skewness ``(f,)`` in [0, 1] of triangles: ``max((θmax − 60)/120, (60 − θmin)/60)``
    with angles in degrees; 0 = equilateral, 1 = degenerate (a zero angle, or a zero-length edge)."""
    return _skewness_of(*_angles_and_lengths(vertices, faces))


def triangle_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(f, 3)`` interior angles of triangles, degrees (angle ``i`` at vertex ``i``)."""
    return _angles_and_lengths(vertices, faces)[0]


#: scipy.stats.skew's thresholds (scipy 1.17 ``_stats_py.skew`` and ``_demean``): below
#: ``max|x − μ| / |μ| < 10 ε`` it warns of catastrophic cancellation, and a second moment
#: ``m2 <= (ε μ)²`` gives NaN; :func:`sample_skewness` hands those cases to scipy itself.
_EPS = float(np.finfo(np.float64).eps)


def sample_skewness(values: np.ndarray) -> float:
    """Statistical (Fisher–Pearson) skewness ``E[(x − μ)³]/σ³`` of the finite values
    (scipy.stats.skew, biased); NaN with fewer than three values or zero spread.

    Computed here with scipy's own operations in its order (``m2 = mean(d²)``,
    ``m3 = mean(d²·d)``, ``m3 / m2**1.5``; ``d = x − mean(x)``): the same float64 bits
    (tests/test_metrics_wiring.py compares on random and near-constant samples) without scipy's
    array-API wrapper, which cost 1.3 ms a call, 6 calls per 3D metrics stage. Where scipy would
    warn or return NaN (:data:`_EPS`), scipy computes it."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < 3 or not np.std(v) > 0:
        return float("nan")
    mean = v.mean()
    d = v - mean
    with np.errstate(divide="ignore", invalid="ignore"):
        cancels = not np.max(np.abs(d)) / abs(mean) >= 10 * _EPS
    m2 = np.mean(d**2)
    if cancels or not m2 > (_EPS * mean) ** 2:
        # start-up: loads scipy (445 ms here); only for near-constant samples
        from scipy.stats import skew

        return float(skew(v))
    return float(np.mean(d**2 * d) / m2**1.5)


def skewness_candidates(
    vertices: np.ndarray, faces: np.ndarray, prefix: str, shape: tuple[np.ndarray, np.ndarray] | None = None
) -> dict[str, float]:
    """Quantities that could be the paper's "skewness" (issue 11; docs/paper.md, "Skewness"):

    * ``{prefix}_aspect_mean``: mean triangle aspect ratio, longest edge over the shortest
      altitude × √3/2 (1 = equilateral), minus 1;
    * ``{prefix}_angle_stat``: |statistical skewness| of all triangle angles;
    * ``{prefix}_equiangle_stat``: |statistical skewness| of the per-triangle equiangle skewness.

    ``shape``: the triangles' ``_angles_and_lengths``, when the caller has them (the 3D metrics
    compute them once per mesh for the skewness summary and these candidates; the same numbers)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return {}
    angles, lengths = _angles_and_lengths(vertices, faces) if shape is None else shape
    v = np.asarray(vertices, dtype=np.float64)[f]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    lmax = lengths.max(axis=1)
    ok = area > 0
    aspect = np.where(ok, lmax * lmax / np.maximum(2 * area, 1e-300) * np.sqrt(3) / 2, np.nan)
    return {
        f"{prefix}_aspect_mean": float(np.nanmean(aspect) - 1.0) if ok.any() else float("nan"),
        f"{prefix}_angle_stat": abs(sample_skewness(angles)),
        f"{prefix}_equiangle_stat": abs(sample_skewness(_skewness_of(angles, lengths))),
    }


def skewness_summary(skew: np.ndarray, prefix: str = "skewness") -> dict[str, float]:
    """Mean, 95th percentile and the share (0–1) of triangles in each ANSYS band."""
    if len(skew) == 0:
        return {}
    out = {f"{prefix}_mean": float(np.mean(skew)), f"{prefix}_p95": float(np.percentile(skew, 95))}
    for name, lo, hi in SKEWNESS_BANDS:
        out[f"{prefix}_share_{name}"] = float(np.mean((skew >= lo) & (skew < hi) & (skew < _DEGENERATE)))
    out[f"{prefix}_share_degenerate"] = float(np.mean(skew >= _DEGENERATE))
    return out


def improvement_rate(rmse_before: float, rmse_after: float) -> float:
    """Eq. (17): ``(RMSE_before − RMSE_after) / RMSE_before × 100`` (percent; > 0 = better).
    Raises ValueError when ``rmse_before`` is not > 0 (the rate is undefined)."""
    if not rmse_before > 0:
        raise ValueError(f"improvement rate undefined for RMSE_before = {rmse_before}")
    return (rmse_before - rmse_after) / rmse_before * 100.0


def geometric_metric_depth(relative: np.ndarray, mask: np.ndarray, distance_m: float, focal_px: float) -> np.ndarray:
    """SFS depth (pixel-pitch units, :mod:`nirspi_pipe.sfs.models`) made metric from the camera
    geometry alone: ``z = z_nom + (z_nom / focal_px) · (d − median(d))`` over ``mask`` (metres).

    ``z_nom / focal_px`` is the pixel pitch at the nominal working distance ``z_nom`` (m); the
    visible surface's median depth is placed at ``z_nom`` (assumed: the camera knows the working
    distance of the set-up, §7: 20 cm, and nothing else). NaN outside ``mask``."""
    d = np.asarray(relative, dtype=np.float64)
    ok = np.asarray(mask, dtype=bool) & np.isfinite(d)
    if not ok.any():
        return np.full(d.shape, np.nan)
    med = float(np.median(d[ok]))
    return np.where(ok, distance_m + distance_m / focal_px * (d - med), np.nan)


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, spacing_m: float, rng: np.random.Generator, max_samples: int = 200_000
) -> np.ndarray:
    """Points on a triangle mesh (metres): the vertices used by its faces plus area-uniform random
    points, about one per ``spacing_m²`` of area (at most ``max_samples``)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 3))
    v = np.asarray(vertices, dtype=np.float64)
    used = v[np.unique(f)]
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    count = int(min(max_samples, np.ceil(total / spacing_m**2))) if total > 0 else 0
    if count == 0:
        return used
    which = rng.choice(len(f), size=count, p=area / total)
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    t = tri[which]
    pts = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
    return np.concatenate([used, pts])


def surface_distances(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Symmetric chamfer distance (mean of the two directed mean distances) and Hausdorff
    distance between point sets ``a`` and ``b`` ``(p, 3)``, in their units.

    The trees are built unbalanced and uncompacted (sliding-midpoint splits): the nearest distances
    are exact either way (the same per-pair arithmetic, whatever the tree), and on the paper's 3D
    jobs (a 32² device mesh of ~5000 samples against the ~19000-point true surface) building and
    querying took 34-89 ms against 39-159 ms balanced (CPU, three Table 3 jobs; the distances
    identical to the bit; ``tests/test_metrics3d_truth.py`` checks it against scipy's brute-force
    distances on random clouds)."""
    da, _ = cKDTree(b, balanced_tree=False, compact_nodes=False).query(a, k=1)
    db, _ = cKDTree(a, balanced_tree=False, compact_nodes=False).query(b, k=1)
    return 0.5 * (float(da.mean()) + float(db.mean())), max(float(da.max()), float(db.max()))


def _to_grid(z: np.ndarray, n: int) -> np.ndarray:
    """``z`` on an ``n × n`` grid: unchanged when it already is, else the NaN-aware mean of its
    ``k × k`` blocks (an SFS depth map of an image upscaled ×k)."""
    if z.shape == (n, n):
        return z
    k = z.shape[0] // n
    if z.shape != (n * k, n * k):
        raise ValueError(f"depth map {z.shape} is not a whole multiple of the {n}x{n} truth grid")
    blocks = z.reshape(n, k, n, k)
    count = np.isfinite(blocks).sum(axis=(1, 3))
    total = np.nansum(blocks, axis=(1, 3))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


_SNAP_PX = 1e-6  # pixels; assumed: 6 orders below a pixel, 10 above the last-bit noise of x/z (~1e-16 px)


def _snap(uv: np.ndarray, focal_px: float) -> np.ndarray:
    """Normalised image coordinates rounded to ``_SNAP_PX`` pixels (returned in pixels)."""
    return np.round(np.asarray(uv, dtype=np.float64) * (focal_px / _SNAP_PX)) * _SNAP_PX


def _interpolate_depth(points: np.ndarray, camera: Camera) -> np.ndarray:
    """z-depth ``(n, n)`` (metres) of a cloud at each pixel centre, linear over the Delaunay
    triangulation of the points' normalised image coordinates; NaN outside their hull.

    Uses matplotlib's triangle finder: scipy's ``Delaunay.find_simplex`` was seen to take
    seconds on these clouds once an OpenCL runtime had been loaded in the process.
    """
    x, y = camera.pixel_coords()
    n = camera.resolution
    p = points[np.isfinite(points).all(axis=1) & (points[:, 2] > 0)]
    if len(p) < 3:
        return np.full((n, n), np.nan)
    # Fused points are back-projected pixels, so many project exactly onto pixel centres and hull
    # edges run through them: inside/outside, the Delaunay diagonal of co-circular points and
    # "repeated point" would then depend on the last bit of x/z, which differs between BLAS kernel
    # sets (AVX-512 vs AVX2). Snap points and pixel centres to 1e-6 pixel (far below any physical
    # scale) so these discrete decisions see identical inputs on every CPU (issue 12).
    uv = _snap(p[:, :2] / p[:, 2:3], camera.focal_px)
    x, y = _snap(x, camera.focal_px), _snap(y, camera.focal_px)
    uv, first = np.unique(uv, axis=0, return_index=True)  # a repeated point breaks a triangulation
    z = p[first, 2]
    if len(uv) < 3:
        return np.full((n, n), np.nan)
    try:
        simplices = Delaunay(uv).simplices
    except QhullError:
        return np.full((n, n), np.nan)
    try:
        tri = mtri.Triangulation(uv[:, 0], uv[:, 1], simplices)
        zi = mtri.LinearTriInterpolator(tri, z)(x[..., 0], y[..., 0])
        return np.ma.filled(zi.astype(np.float64), np.nan).reshape(n, n)
    except (RuntimeError, ValueError):  # matplotlib rejects near-degenerate triangulations
        from scipy.interpolate import LinearNDInterpolator  # start-up: loads scipy (90 ms here)

        return LinearNDInterpolator(uv, z)(x[..., 0], y[..., 0]).reshape(n, n)


def _sfs_depths(
    truth: Scene, depth: DepthMap | None, cloud: PointCloud | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The SFS depth (m, on its own grid) made metric by the camera geometry alone and by the
    fusion's global fit (module docstring); each None when it cannot be made."""
    z_sfs = z_geom = None
    if depth is not None and not depth.metric:
        cam = truth.camera
        grid = cam if depth.depth_m.shape[0] == cam.resolution else cam.resampled(depth.depth_m.shape[0])
        z_geom = geometric_metric_depth(depth.depth_m, depth.mask, float(truth.distance_m), grid.focal_px)
    if depth is not None and (depth.metric or (cloud is not None and cloud.depth_scale is not None)):
        zr = np.asarray(depth.depth_m, dtype=np.float64)
        if depth.metric:
            z_sfs = zr
        else:
            assert cloud is not None and cloud.depth_scale is not None
            z_sfs = cloud.depth_scale * zr + float(cloud.depth_offset_m or 0.0)
        z_sfs = np.where(np.asarray(depth.mask, dtype=bool) & np.isfinite(z_sfs), z_sfs, np.nan)
    return z_geom, z_sfs


def compared_depths(
    truth: Scene, depth: DepthMap | None, cloud: PointCloud | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """What Eq. (16) compares, on ``truth``'s grid: the pixels where the truth, the SFS and the
    fused depth all exist, and the SFS depth made metric by the camera geometry alone
    (``depth_rmse_sfs_mm``), by the fusion's global fit (``depth_rmse_sfs_fit_mm``) and the fused
    depth (``depth_rmse_fused_mm``), in metres. None without SFS depth or fused cloud.
    ``summary.png`` plots the same errors (:mod:`nirspi_pipe.figure`)."""
    z_geom, z_sfs = _sfs_depths(truth, depth, cloud)
    if z_sfs is None or cloud is None:
        return None
    cam = truth.camera
    z_sfs = _to_grid(z_sfs, cam.resolution)  # an upscaled SFS grid is scored on the truth's
    z_base = _to_grid(z_geom, cam.resolution) if z_geom is not None else z_sfs
    z_fused = _interpolate_depth(np.asarray(cloud.points_m), cam)
    tmask = truth.mask & np.isfinite(truth.depth_m)
    both = tmask & np.isfinite(z_sfs) & np.isfinite(z_fused) & np.isfinite(z_base)
    return both, z_base, z_sfs, z_fused


def depth_truth(truth: Scene, depth: DepthMap | None, scene_model: Any) -> Scene:
    """The ground truth that depth is scored against: ``truth`` itself when the SFS depth is on
    its grid (or there is no scene model to render), else ``scene_model`` rendered again on the
    SFS depth's grid, same field of view (an upscaled run: the device's 8² camera, depth on the
    32² grid). The 3D metrics, ``summary.png`` and ``mesh.png`` all use this one grid."""
    if depth is None or scene_model is None or depth.depth_m.shape[0] == truth.camera.resolution:
        return truth
    from nirspi_pipe.upscale.data import RenderCamera  # start-up: loads scipy (66 ms here)

    side = int(depth.depth_m.shape[0])
    return render_cached(scene_model, RenderCamera(resolution=side, fov_deg=truth.camera.fov_deg))


def run_depth_truth(products: Products, config: Any) -> Scene | None:
    """:func:`depth_truth` of a finished run from its resolved config (plain data): the scene
    model is the run's ``scene``; only an upscaled run is scored on a finer grid
    (:class:`Metrics3D`). None without a ground truth."""
    truth = products.truth
    if truth is None or products.upscaled is None or products.depth is None:
        return truth
    if products.depth.depth_m.shape[0] == truth.camera.resolution:
        return truth
    node = (config or {}).get("scene")
    if not (isinstance(node, dict) and "_target_" in node):
        return truth

    return depth_truth(truth, products.depth, build(node, "scene"))


@dataclass(frozen=True)
class Metrics3D:
    """Metrics ``full``: SSIM/PSNR/RMSE of the 2D image plus the 3D metrics (module docstring).

    Attributes:
        names: the 2D image metrics (subset of ``ssim``, ``psnr``, ``rmse``).
        clip: clip the 2D reconstruction to [0, 1] before scoring.
        sample_spacing_mm: surface sampling for chamfer/Hausdorff, mm; null = half the true
            pixel pitch at the scene distance.
        surface_distances: compute ``chamfer_mm`` and ``hausdorff_mm`` (default). ``false``
            leaves them out of the record: they are the costliest 3D scores (the paper's Table 3
            jobs spend about two thirds of their metrics stage on them, docs/mesh.md), and no
            table of the paper reports them, so the paper's experiments turn them off.
        scene, source: the run's scene model and source; with an upscaled image they give the
            scores on the upscaled grid (module docstring). Not config keys: the runner hands
            over the stages it built (:meth:`with_stages`).
    """

    names: tuple[str, ...] = field(default=("ssim", "psnr", "rmse"))
    clip: bool = False
    sample_spacing_mm: float | None = None
    surface_distances: bool = True
    scene: Any = field(default=None, repr=False, compare=False, metadata={"config": False})
    source: Any = field(default=None, repr=False, compare=False, metadata={"config": False})

    def __post_init__(self) -> None:
        ImageMetrics(tuple(self.names), self.clip)  # validates names
        if self.sample_spacing_mm is not None and not self.sample_spacing_mm > 0:
            raise ConfigError("sample_spacing_mm", self.sample_spacing_mm, "a spacing in mm > 0, or null")

    def with_stages(self, stages: RunStages) -> Metrics3D:
        """These metrics with the run's built scene model and source
        (:class:`~nirspi_pipe.stages.ScoresWithStages`; the upscaler is not used: no ``noise_*``
        scores here)."""
        return replace(self, scene=stages.scene, source=stages.source)

    def compute(self, products: Products) -> dict[str, float]:
        """All metrics that the run's products allow (3D ones need truth, depth, cloud, mesh)."""
        fine = products.upscaled is not None and self.scene is not None and products.truth is not None
        if fine:
            from nirspi_pipe.upscale.metrics import UpscaleMetrics  # start-up: loads scipy (70 ms here)

            out = UpscaleMetrics(tuple(self.names), self.clip, scene=self.scene, source=self.source).compute(products)
        else:
            out = ImageMetrics(tuple(self.names), self.clip).compute(products)
        truth = products.truth
        if truth is None:
            return out
        depth = products.depth
        if fine:
            truth = depth_truth(truth, depth, self.scene)
        cloud, mesh = products.cloud, products.mesh
        _, z_sfs = _sfs_depths(truth, depth, cloud)
        if z_sfs is not None:
            out.update(_sfs_skewness(truth.camera, z_sfs))
        compared = compared_depths(truth, depth, cloud)
        surface = truth_surface(truth, self.scene) if compared is not None or mesh is not None else None
        if compared is not None:
            out.update(_depth_scores(truth, compared))
            assert surface is not None
            out.update(_inner_depth_scores(truth, compared, inner_pixels(surface, truth.depth_m.shape)))
        if mesh is not None and len(mesh.faces):
            assert surface is not None
            out.update(self._mesh_scores(truth, mesh, surface))
        elif mesh is not None:
            warnings.warn("metrics: the mesh has no face; no skewness or surface distance", stacklevel=2)
        return out

    def _mesh_scores(self, truth: Any, mesh: Any, surface: TruthSurface) -> dict[str, float]:
        """The mesh's equiangle skewness (summary and candidates) and, where the true surface has
        samples and :attr:`surface_distances` is on, its chamfer and Hausdorff distances to it (mm)."""
        shape = _angles_and_lengths(mesh.vertices_m, mesh.faces)  # once: the summary and the candidates
        out = dict(skewness_summary(_skewness_of(*shape)))
        out.update(
            {
                k: v
                for k, v in skewness_candidates(mesh.vertices_m, mesh.faces, "cand_mesh", shape).items()
                if np.isfinite(v)
            }
        )
        if not self.surface_distances:
            return out
        truth_pts = surface.cloud()
        if len(truth_pts):
            pitch = truth.distance_m / truth.camera.focal_px
            spacing = self.sample_spacing_mm * 1e-3 if self.sample_spacing_mm is not None else pitch / 2
            rng = np.random.default_rng(0)  # fixed: a metric must not vary between runs
            mesh_pts = sample_surface(mesh.vertices_m, mesh.faces, spacing, rng)
            chamfer, hausdorff = surface_distances(mesh_pts, truth_pts)
            out.update(chamfer_mm=chamfer * 1e3, hausdorff_mm=hausdorff * 1e3)
        return out


def _sfs_skewness(cam: Camera, z_sfs: np.ndarray) -> dict[str, float]:
    """The SFS depth map's grid mesh: its mean and 95th-percentile equiangle skewness and the
    skewness candidates; empty when no face has three valid pixels."""
    sfs_valid = np.isfinite(z_sfs) & (z_sfs > 0)
    faces = grid_triangles(sfs_valid)
    if not len(faces):
        return {}
    sfs_cam = cam if z_sfs.shape[0] == cam.resolution else cam.resampled(z_sfs.shape[0])
    verts = back_project(np.where(sfs_valid, z_sfs, 0.0), sfs_cam).reshape(-1, 3)
    shape = _angles_and_lengths(verts, faces)  # once: the summary and the candidates
    out = {
        k: v
        for k, v in skewness_summary(_skewness_of(*shape), "skewness_sfs").items()
        if k in ("skewness_sfs_mean", "skewness_sfs_p95")
    }
    out.update(skewness_candidates(verts, faces, "cand_sfs", shape))
    return out


def _depth_scores(truth: Any, compared: tuple[np.ndarray, ...]) -> dict[str, float]:
    """Eq. (16)'s depth RMSEs (mm) of the SFS baselines and the fused depth on the pixels they
    share, Eq. (17)'s improvements and the error skewness candidates; warns (for the caller of
    :meth:`Metrics3D.compute`) where no pixel is shared or the baseline's RMSE is 0."""
    out: dict[str, float] = {}
    both, z_base, z_sfs, z_fused = compared
    if not both.any():
        warnings.warn("metrics: no pixel where truth, SFS and fused depth all exist", stacklevel=3)
        return out
    fit = rmse(z_sfs[both], truth.depth_m[both])  # Eq. (16), global-fit baseline
    before = rmse(z_base[both], truth.depth_m[both])  # Eq. (16), geometric baseline
    after = rmse(z_fused[both], truth.depth_m[both])
    offset = float(np.mean(truth.depth_m[both] - z_base[both]))  # least-squares constant
    free = rmse(z_base[both] + offset, truth.depth_m[both])  # offset-free baseline
    out.update(
        depth_rmse_sfs_mm=before * 1e3,
        depth_rmse_sfs_offsetfree_mm=free * 1e3,
        sfs_offset_mm=offset * 1e3,
        depth_rmse_sfs_fit_mm=fit * 1e3,
        depth_rmse_fused_mm=after * 1e3,
        depth_pixels=float(both.sum()),
    )
    # skewness candidates: |statistical skewness| of the depth errors (docs/paper.md)
    for key, z in (("cand_sfs_error_stat", z_sfs), ("cand_mesh_error_stat", z_fused)):
        val = abs(sample_skewness(z[both] - truth.depth_m[both]))
        if np.isfinite(val):
            out[key] = val
    if before > 0 and fit > 0:
        out["improvement_pct"] = improvement_rate(before, after)  # Eq. (17)
        out["improvement_fit_pct"] = improvement_rate(fit, after)
        if free > 0:
            out["improvement_offsetfree_pct"] = improvement_rate(free, after)
    else:
        warnings.warn("metrics: SFS depth RMSE is 0; improvement rate undefined", stacklevel=3)
    return out


def _inner_depth_scores(truth: Any, compared: tuple[np.ndarray, ...], inner: np.ndarray | None) -> dict[str, float]:
    """``depth_rmse_fused_inner_mm`` on the compared pixels fully inside one surface, their count
    and share of the compared pixels (module docstring); empty without a fine truth (``inner``
    None) or without compared pixels. The RMSE is absent where no compared pixel is inner."""
    both, _, _, z_fused = compared
    if inner is None or not both.any():
        return {}
    keep = both & inner
    out = {"depth_inner_pixels": float(keep.sum()), "depth_inner_share": float(keep.sum() / both.sum())}
    if keep.any():
        out["depth_rmse_fused_inner_mm"] = rmse(z_fused[keep], truth.depth_m[keep]) * 1e3
    return out
