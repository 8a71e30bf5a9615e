"""3D metrics: equiangle skewness, Eq. (17), surface distances, Metrics3D on a 3D run."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.mesh.metrics3d import (
    Metrics3D,
    equiangle_skewness,
    improvement_rate,
    skewness_candidates,
    skewness_summary,
    surface_distances,
)


def test_skewness_reference_triangles():
    eq = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    t306090 = np.array([[0, 0, 0], [np.sqrt(3), 0, 0], [0, 1, 0]])
    collinear = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    point = np.zeros((3, 3))
    for v, expected in ((eq, 0.0), (t306090, 0.5), (collinear, 1.0), (point, 1.0)):
        assert equiangle_skewness(v, np.array([[0, 1, 2]]))[0] == pytest.approx(expected, abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=9, max_size=9))
def test_skewness_in_unit_interval(coords):
    s = equiangle_skewness(np.array(coords).reshape(3, 3), np.array([[0, 1, 2]]))
    assert np.all(np.isfinite(s)) and 0.0 <= s[0] <= 1.0


def _reference_angles(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Interior angles (degrees) written out independently: the law of cosines on edge lengths."""
    p = v[f]
    a = np.linalg.norm(p[:, 1] - p[:, 2], axis=1)  # opposite vertex 0
    b = np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    c = np.linalg.norm(p[:, 0] - p[:, 1], axis=1)
    cos0 = (b**2 + c**2 - a**2) / (2 * b * c)
    cos1 = (a**2 + c**2 - b**2) / (2 * a * c)
    return np.degrees(np.arccos(np.clip(np.stack([cos0, cos1], axis=1), -1, 1)))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 40), st.integers(1, 80))
def test_skewness_shapes_computed_once_give_the_same_numbers(seed: int, n: int, m: int) -> None:
    """The 3D metrics compute each mesh's angles once for the skewness summary and the candidates
    (issue 42 item 6): with the shared angles the candidates are the same bits as without, and the
    angles are the triangles' (law of cosines, away from degenerate triangles)."""
    from nirspi_pipe.mesh.metrics3d import _angles_and_lengths, triangle_angles

    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    f = rng.integers(0, n, size=(m, 3))
    shape = _angles_and_lengths(v, f)
    alone, shared = skewness_candidates(v, f, "x"), skewness_candidates(v, f, "x", shape)
    assert alone.keys() == shared.keys()
    for key in alone:
        assert np.array_equal(alone[key], shared[key], equal_nan=True), key
    ang = triangle_angles(v, f)
    assert np.array_equal(ang, shape[0])
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if good.any():
        np.testing.assert_allclose(ang[good, :2], _reference_angles(v, f[good]), atol=1e-4)
        np.testing.assert_allclose(ang[good].sum(axis=1), 180.0, atol=1e-6)


def test_bands_partition():
    s = np.array([0.0, 0.1, 0.3, 0.6, 0.8, 0.95, 1.0])
    out = skewness_summary(s)
    shares = [v for k, v in out.items() if "_share_" in k]
    assert sum(shares) == pytest.approx(1.0)
    assert out["skewness_share_degenerate"] == pytest.approx(1 / 7)
    assert out["skewness_share_excellent"] == pytest.approx(2 / 7)


def test_improvement_rate_sign():
    assert improvement_rate(2.0, 1.0) == pytest.approx(50.0)
    assert improvement_rate(1.0, 1.5) == pytest.approx(-50.0)
    with pytest.raises(ValueError):
        improvement_rate(0.0, 1.0)


def test_surface_distances():
    a = np.random.default_rng(0).random((50, 3))
    assert surface_distances(a, a) == (0.0, 0.0)
    c, h = surface_distances(a, a + [0, 0, 0.1])
    assert c == pytest.approx(0.1, rel=0.05) and h >= c


def test_bad_names():
    with pytest.raises(ConfigError):
        Metrics3D(names=("nope",))


def test_metrics3d_on_a_3d_run():
    from nirspi_pipe.itof.cw4 import ContinuousWave4
    from nirspi_pipe.mesh.fusion import ItofFusion
    from nirspi_pipe.mesh.powercrust import PowerCrust
    from nirspi_pipe.mesh.standin import degraded_depth
    from nirspi_pipe.scene.objects import Sphere
    from nirspi_pipe.stages import Products
    from nirspi_pipe.types import Acquisition, Camera, Image2D

    scene = Sphere().render(Camera(64))
    # the 2D image below is the truth: a stand-in for a reconstruction from every pattern (the
    # normalised scores count the patterns an image could carry, metrics.measured_values)
    acq = Acquisition(n=64, indices=np.arange(64 * 64), y_pos=np.zeros(64 * 64), truth=scene)
    rng = np.random.default_rng(0)
    depth = degraded_depth(scene, rng, noise_px=1.0, outlier_fraction=0.05)
    itof = ContinuousWave4(averaging_s=500.0).measure(scene, acq, rng)
    cloud = ItofFusion().fuse(depth, itof, scene.camera)
    mesh = PowerCrust().reconstruct(cloud)
    m = Metrics3D().compute(Products(scene, acq, Image2D(scene.radiance), None, depth, itof, cloud, mesh))
    for key in (
        "depth_rmse_sfs_mm",
        "depth_rmse_fused_mm",
        "improvement_pct",
        "skewness_mean",
        "skewness_p95",
        "chamfer_mm",
        "hausdorff_mm",
        "skewness_sfs_mean",
    ):
        assert np.isfinite(m[key]), key
    assert m["improvement_pct"] > 20  # outliers and noise removed
    assert m["chamfer_mm"] < 1.5 and m["hausdorff_mm"] >= m["chamfer_mm"]
    assert m["depth_pixels"] > 1000
    # a 2D-only run gets the image metrics only
    only2d = Metrics3D().compute(Products(scene, acq, Image2D(scene.radiance)))
    assert set(only2d) == {"ssim", "psnr", "rmse", "ssim_raw", "psnr_raw"}


def test_depth_interpolation_survives_degenerate_clouds() -> None:
    """A cloud with repeated and collinear points (seen in a torus run) must not raise."""
    from nirspi_pipe.mesh.metrics3d import _interpolate_depth
    from nirspi_pipe.types import Camera

    cam = Camera(resolution=16)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.02, 0.02, (40, 2)), rng.uniform(0.19, 0.21, 40)])
    pts = np.vstack([pts, pts[:10], [[0.0, 0.0, 0.2], [1e-12, 0.0, 0.2], [2e-12, 0.0, 0.2]]])
    z = _interpolate_depth(pts, cam)
    assert z.shape == (16, 16)
    inside = np.isfinite(z)
    assert inside.any() and np.all((z[inside] > 0.18) & (z[inside] < 0.22))
    line = np.array([[0.0, 0.0, 0.2], [0.01, 0.0, 0.2], [0.02, 0.0, 0.2]])
    assert np.isnan(_interpolate_depth(line, cam)).all()  # no area: nothing to interpolate


def test_geometric_baseline_uses_the_camera_geometry_only():
    """The no-iToF baseline of Eq. (17): pixel-pitch depth scaled by z_nom/focal_px, median at z_nom."""
    from nirspi_pipe.mesh.metrics3d import geometric_metric_depth

    d = np.array([[0.0, 1.0], [2.0, np.nan]])
    mask = np.array([[True, True], [True, True]])
    z = geometric_metric_depth(d, mask, 0.2, 100.0)
    assert np.isclose(np.nanmedian(z), 0.2) and np.isnan(z[1, 1])
    assert np.isclose(z[1, 0] - z[0, 0], 2 * 0.2 / 100.0)
    assert np.isnan(geometric_metric_depth(d, np.zeros((2, 2), bool), 0.2, 100.0)).all()
