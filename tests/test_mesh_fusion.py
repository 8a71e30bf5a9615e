"""Fusion itof (Algs. A3/A4): metric recovery, Eqs. 13-15, voxels, diffusion, degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.itof.cw4 import ContinuousWave4
from nirspi_pipe.mesh.anchors import fit_anchors, region_weights
from nirspi_pipe.mesh.fusion import ItofFusion
from nirspi_pipe.mesh.pointcloud import heat_diffusion, semi_even_points, voxel_merge
from nirspi_pipe.mesh.standin import degraded_depth
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Acquisition, Camera, DepthMap, ItofSample

CENTRE, RADIUS = np.array([0.0, 0.0, 0.2]), 0.025


@pytest.fixture(scope="module")
def scene():
    return Sphere().render(Camera(64))


def _itof(scene, seed=0, averaging_s=50.0):
    acq = Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1))
    return ContinuousWave4(averaging_s=averaging_s).measure(scene, acq, np.random.default_rng(seed))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_metric_sphere(scene, seed):
    """SFS-like depth with 10 % scale error, an offset of 37 px, 0.3 px noise and 2 % outliers of
    8 px: with 1.4 mm iToF anchors the metric depth is within 2.5 mm RMS of the truth and the
    fused cloud within 2 mm RMS of the sphere."""
    rng = np.random.default_rng(seed)
    depth = degraded_depth(scene, rng)
    itof = _itof(scene, seed)
    fusion = ItofFusion()
    z, valid, fit = fusion.metric_depth(depth, itof, scene.camera)
    m = valid & scene.mask
    assert np.sqrt(np.mean((z[m] - scene.depth_m[m]) ** 2)) < 2.5e-3
    cloud = fusion.fuse(depth, itof, scene.camera)
    d = np.linalg.norm(cloud.points_m - CENTRE, axis=1) - RADIUS
    assert np.sqrt(np.mean(d**2)) < 2e-3
    assert cloud.info["anchors_used"] == 4 and np.all(np.isfinite(cloud.normals))
    assert np.all(cloud.normals @ np.array([0, 0, 1.0]) < 0.5)  # normals face the camera
    # automatic voxel of 2 pixel pitches: about one point per 2x2 pixels of the cap
    assert 0.15 * cloud.info["pixels"] < len(cloud.points_m) < 0.6 * cloud.info["pixels"]


def test_fused_depth_is_smoother_than_sfs(scene):
    from nirspi_pipe.mesh.metrics3d import _interpolate_depth

    rng = np.random.default_rng(5)
    depth = degraded_depth(scene, rng, noise_px=1.0, outlier_fraction=0.05)
    itof = _itof(scene, 5, averaging_s=500.0)
    fusion = ItofFusion()
    cloud = fusion.fuse(depth, itof, scene.camera)
    # SFS made metric with the same global scale and offset (what Metrics3D calls "before")
    assert cloud.depth_scale == cloud.info["scale"] and cloud.depth_offset_m == cloud.info["offset_m"]
    z = cloud.depth_scale * depth.depth_m + cloud.depth_offset_m
    zf = _interpolate_depth(cloud.points_m, scene.camera)
    m = depth.mask & scene.mask & np.isfinite(zf)
    before = np.sqrt(np.mean((z[m] - scene.depth_m[m]) ** 2))
    after = np.sqrt(np.mean((zf[m] - scene.depth_m[m]) ** 2))
    assert after < 0.8 * before


def test_semi_even_points_on_a_triangle():
    tri = np.array([[[0, 0, 0], [0.05, 0, 0], [0, 0.03, 0]]], dtype=float)
    d = 0.005
    p = semi_even_points(tri, tri[:, 0], d)
    area = 0.5 * 0.05 * 0.03
    assert 0.6 * area / d**2 < len(p) < 1.6 * area / d**2
    # inside the triangle (barycentric), rows d apart, V0 included
    assert np.all(p[:, 0] >= -1e-12) and np.all(p[:, 1] >= -1e-12)
    assert np.all(p[:, 0] / 0.05 + p[:, 1] / 0.03 <= 1 + 1e-9)
    assert np.any(np.all(p == 0, axis=1))
    from scipy.spatial import cKDTree

    nn = cKDTree(p).query(p, k=2)[0][:, 1]
    assert nn.min() >= d * (1 - 1e-9)


def test_eq15_alpha_guard_sliver():
    # alpha -> 0: d/sin(alpha) would blow up; the guard keeps it finite and small
    tri = np.array([[[0, 0, 0], [0.05, 0, 0], [0.05, 1e-12, 0]]], dtype=float)
    p = semi_even_points(tri, tri[:, 0], 0.005)
    assert np.all(np.isfinite(p)) and 1 <= len(p) <= 20


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.floats(-0.05, 0.05, allow_nan=False), min_size=9, max_size=9),
    st.sampled_from(["generic", "collinear", "point", "edge"]),
)
def test_semi_even_points_degenerate_geometry(coords, kind):
    tri = np.array(coords, dtype=float).reshape(1, 3, 3)
    if kind == "collinear":
        tri[0, 2] = tri[0, 0] + 0.3 * (tri[0, 1] - tri[0, 0])
    elif kind == "point":
        tri[0, 1] = tri[0, 2] = tri[0, 0]
    elif kind == "edge":
        tri[0, 2] = tri[0, 1]
    p = semi_even_points(tri, tri[:, 0], 0.004)
    assert len(p) >= 1 and np.all(np.isfinite(p))
    # every point stays in the triangle's bounding box
    lo, hi = tri[0].min(axis=0) - 1e-12, tri[0].max(axis=0) + 1e-12
    assert np.all((p >= lo) & (p <= hi))


def test_voxel_merge_averages():
    pts = np.array([[0.001, 0.001, 0.001], [0.003, 0.003, 0.003], [0.011, 0.0, 0.0]])
    out = voxel_merge(pts, 0.005)
    assert len(out) == 2
    assert np.allclose(sorted(out[:, 0]), [0.002, 0.011])


def test_region_weights_partition_of_unity():
    anchors = np.array([45.0, 135.0, -135.0, -45.0])
    ang = np.linspace(-180, 180, 721)
    for blend in (0.0, 30.0, 90.0):
        w = region_weights(ang, anchors, blend)
        assert np.allclose(w.sum(axis=-1), 1.0) and np.all(w >= 0)
    hard = region_weights(np.array([10.0, 100.0]), anchors, 0.0)
    assert np.argmax(hard, axis=-1).tolist() == [0, 1]


def test_heat_diffusion_smooths_noise_and_t0_is_identity():
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(20), np.arange(20)), -1).reshape(-1, 2) * 0.005
    pts = np.column_stack([g, np.full(len(g), 0.2)])
    z = 0.2 + rng.normal(0, 1e-3, len(g))
    out = heat_diffusion(z, pts, 8, 2.0)
    assert np.std(out - 0.2) < 0.6 * np.std(z - 0.2)
    assert abs(out.mean() - z.mean()) < 1e-4  # heat is conserved (up to degree weighting)
    assert np.array_equal(heat_diffusion(z, pts, 8, 0.0), z)


def test_collinear_anchors_need_scale_prior():
    zr = np.array([10.0, 10.0, 10.0, 10.0])
    z = np.array([0.18, 0.181, 0.179, 0.18])
    sig = np.full(4, 0.01)
    with pytest.raises(NirspiError, match="scale"):
        fit_anchors(zr, z, sig, 10.0, 180.0, None)
    fit = fit_anchors(zr, z, sig, 10.0, 180.0, 0.2)
    assert fit.scale == pytest.approx(fit.placement_m / 180.0) and fit.placement_m == pytest.approx(0.18)


def test_no_anchor_is_clear_error():
    with pytest.raises(NirspiError, match="no valid iToF anchor"):
        fit_anchors(np.zeros(0), np.zeros(0), np.zeros(0), 0.0, 180.0, 0.2)
    # with a placement prior, no anchor places the depth at the prior, at the geometric scale
    fit = fit_anchors(np.zeros(0), np.zeros(0), np.zeros(0), 0.0, 180.0, None, 0.2, 0.05)
    assert fit.placement_m == pytest.approx(0.2) and fit.scale == pytest.approx(0.2 / 180.0)
    assert fit.placement_sigma_m == pytest.approx(0.05, rel=1e-6)


def test_empty_mask_and_missing_itof(scene):
    itof = _itof(scene)
    empty = DepthMap(depth_m=np.zeros((64, 64)), mask=np.zeros((64, 64), bool))
    with pytest.raises(NirspiError, match="no valid pixel"):
        ItofFusion().fuse(empty, itof, scene.camera)
    with pytest.raises(ConfigError, match="itof"):
        ItofFusion().fuse(degraded_depth(scene, np.random.default_rng(0)), None, scene.camera)


def test_all_spots_invalid_is_clear_error(scene):
    bad = ItofSample(points_m=np.ones((4, 3)), sigma_m=np.full(4, np.inf))
    with pytest.warns(UserWarning, match="no valid range"):
        with pytest.raises(NirspiError, match="no valid iToF anchor"):
            ItofFusion().fuse(degraded_depth(scene, np.random.default_rng(0)), bad, scene.camera)


def test_nan_inside_mask_is_warned(scene):
    depth = degraded_depth(scene, np.random.default_rng(0))
    d = depth.depth_m.copy()
    d[32, 32] = np.nan
    with pytest.warns(UserWarning, match="not finite"):
        cloud = ItofFusion().fuse(DepthMap(d, depth.mask), _itof(scene), scene.camera)
    assert np.all(np.isfinite(cloud.points_m))


@pytest.mark.parametrize(
    "key,value",
    [
        ("d_pitch_mm", 0.0),
        ("min_angle_deg", 0.0),
        ("knn", 2),
        ("time_step", -1.0),
        ("diffuse", "z"),
        ("blend_px", -1.0),
        ("scale_prior_rel", 0.0),
    ],
)
def test_bad_config(key, value):
    with pytest.raises(ConfigError, match=key):
        ItofFusion(**{key: value})
