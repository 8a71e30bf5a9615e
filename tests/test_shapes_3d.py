"""Issue 14: 3D on shapes nobody tuned for (generated shape set end to end, aimed iToF spots,
1-4 anchors, singular regions, fusion that never hurts, remeshing, a voxel that scales)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.itof.cw4 import ContinuousWave4, aim_spots
from nirspi_pipe.mesh.anchors import depth_noise
from nirspi_pipe.mesh.fusion import ItofFusion
from nirspi_pipe.mesh.metrics3d import equiangle_skewness
from nirspi_pipe.mesh.powercrust import PowerCrust
from nirspi_pipe.mesh.remesh import clean_and_remesh
from nirspi_pipe.mesh.standin import degraded_depth
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.scene.testshapes import KINDS, GeneratedShape, vase_profile
from nirspi_pipe.sfs.models import LaxFriedrichsSFS
from nirspi_pipe.types import Acquisition, Camera, Image2D, ItofSample

CAM = Camera(64)


def _acq() -> Acquisition:
    return Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1))


def _cfg(*overrides: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        # noise-free and 64², whatever the default run is (conf/config.yaml); the compose API takes
        # preset=off where nirspi-run also takes preset=null
        return compose(
            "config", overrides=["fog=none", "illumination=none", "detector=ideal", "preset=off", *overrides]
        )


# -- the shape set end to end ---------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_shape_set_end_to_end(kind):
    """Noise-free, 64²: every shape runs the whole 3D path; fusion never hurts (Eq. 17 >= -2 %),
    the remeshed power crust has mean equiangle skewness <= 0.32, the anchors are found.

    0.32: the seven shapes measure 0.24-0.30, and a change of
    rounding alone in the pole computation (LU solve -> Cramer's rule, issue 12) moved single
    shapes by up to 0.011 (plate_edge 0.290 -> 0.301): isotropic remeshing is sensitive to the last
    bits of its input, so the bound keeps two such steps of margin above the worst shape."""
    from nirspi_pipe.pipeline import run_pipeline

    out = run_pipeline(
        _cfg(f"scene={kind}", "sfs=second_order", "itof=cw4", "fusion=itof", "surface=power_crust", "metrics=full")
    )
    m = out.metrics
    for key in (
        "depth_rmse_sfs_mm",
        "depth_rmse_fused_mm",
        "improvement_pct",
        "chamfer_mm",
        "hausdorff_mm",
        "skewness_mean",
    ):
        assert np.isfinite(m[key]), key
    assert m["improvement_pct"] >= -2.0
    assert m["skewness_mean"] <= 0.32
    assert out.info["fusion"]["anchors_used"] >= 3
    assert out.info["itof"]["aimed"]


def test_shape_bad_config():
    with pytest.raises(ConfigError, match="kind"):
        GeneratedShape(kind="teapot")
    with pytest.raises(ConfigError, match="size_mm"):
        GeneratedShape(size_mm=300.0, distance_mm=200.0)
    with pytest.raises(ConfigError, match="offset_mm"):
        GeneratedShape(offset_mm=(1.0, np.nan))


# -- iToF spots -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["plate_edge", "multi", "off_centre", "partial", "ring"])
def test_auto_spots_land_on_the_object(kind):
    rot = {"plate_edge": (0.0, 75.0, 0.0), "ring": (30.0, 0.0, 0.0)}.get(kind, (0.0, 0.0, 0.0))
    scene = GeneratedShape(kind=kind, rotation_deg=rot, supersample=2).render(CAM)
    px, notes = aim_spots(scene.radiance, CAM, 4, 0.1)
    assert len(px) == 4 and not notes
    assert scene.mask[px[:, 0], px[:, 1]].all()
    it = ContinuousWave4().aimed(Image2D(scene.radiance), CAM)
    sample = it.measure(scene, _acq(), np.random.default_rng(0))
    assert np.isfinite(sample.sigma_m).all()  # every spot returns
    if kind == "multi":  # each separate object gets a spot
        from scipy import ndimage

        lab, n = ndimage.label(scene.mask)
        assert n == 3 and set(lab[px[:, 0], px[:, 1]]) == {1, 2, 3}


def test_fixed_spots_miss_a_thin_plate_and_auto_does_not():
    scene = GeneratedShape(kind="plate_edge", rotation_deg=(0.0, 75.0, 0.0), supersample=2).render(CAM)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fixed = ContinuousWave4(spots="fixed").measure(scene, _acq(), np.random.default_rng(0))
    assert np.isinf(fixed.sigma_m).sum() >= 2  # the paper's geometry misses the plate
    aimed = ContinuousWave4().aimed(Image2D(scene.radiance), CAM).measure(scene, _acq(), np.random.default_rng(0))
    assert np.isfinite(aimed.sigma_m).all()


def test_spot_config_errors():
    for key, value in [
        ("spots", "laser"),
        ("n_spots", 0),
        ("n_spots", 5),
        ("aim_threshold", 1.5),
        ("aim_directions", ((0.0, 0.0, -1.0),)),
    ]:
        with pytest.raises(ConfigError, match=key):
            ContinuousWave4(**{key: value})


def test_dark_image_falls_back_to_fixed_with_warning():
    with pytest.warns(UserWarning, match="no object to aim at"):
        it = ContinuousWave4().aimed(Image2D(np.zeros((64, 64))), CAM)
    assert it.aim_directions is None


# -- fusion with 1-4 anchors ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sphere():
    return Sphere().render(CAM)


@pytest.mark.parametrize("n_valid", [1, 2, 3, 4])
def test_fusion_with_one_to_four_anchors(sphere, n_valid):
    """1 anchor: offset; 2: offset and scale; >= 3: also local offsets. The metric depth stays
    within 3 mm RMS of the truth with 1.4 mm anchors."""
    depth = degraded_depth(sphere, np.random.default_rng(0))
    s = ContinuousWave4(averaging_s=50.0).measure(sphere, _acq(), np.random.default_rng(0))
    sig = s.sigma_m.copy()
    sig[n_valid:] = np.inf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        z, valid, fit = ItofFusion().metric_depth(depth, ItofSample(s.points_m, sig), CAM)
    assert fit["anchors_used"] == n_valid
    assert len(fit["anchors_rejected"]) == 4 - n_valid
    assert all("no valid range" in r for r in fit["anchors_rejected"].values())
    assert sum("not used" in str(w.message) for w in caught) == 4 - n_valid
    if n_valid < 3:
        assert not any(fit["region_offsets_m"])
    m = valid & sphere.mask
    assert np.sqrt(np.mean((z[m] - sphere.depth_m[m]) ** 2)) < 3e-3


def test_no_anchor_error_names_every_reason(sphere):
    depth = degraded_depth(sphere, np.random.default_rng(0))
    far = ItofSample(points_m=np.array([[0.03, 0.03, 0.2], [1.0, 1.0, np.nan]]), sigma_m=np.array([0.01, np.inf]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(
            NirspiError, match=r"spot 0: falls at pixel .* outside the SFS depth mask.*spot 1: no valid"
        ):
            ItofFusion().fuse(depth, far, CAM)


def test_failed_record_keeps_its_warnings(tmp_path):
    from nirspi_pipe.app.jobs import execute_job

    # one spot aimed off the object: fusion has no anchor and, without the working-distance prior
    # (which would place the depth alone, with a warning), the job fails
    cfg = _cfg(
        "itof=cw4",
        "itof.aim_directions=[[0.15,0.15,0.98]]",
        "sfs=second_order",
        "fusion=itof",
        "fusion.prior_distance_mm=null",
        "output.images=false",
        "output.arrays=false",
    )
    record = execute_job(cfg, tmp_path, {}, [])
    assert record["meta"]["status"] == "failed"
    assert "no valid iToF anchor" in record["meta"]["error"]
    assert any("itof: laser 0 has no valid return" in w for w in record["meta"]["warnings"])
    assert any("fusion: iToF spot 0 not used" in w for w in record["meta"]["warnings"])


def test_local_offsets_shrink_where_sfs_and_itof_agree(sphere):
    """Anchors that agree with the SFS within their noise get no local correction; one 30 mm off
    (beyond 3 sigma) gets most of it."""
    from nirspi_pipe.types import DepthMap

    zpx = sphere.depth_m / (0.2 / CAM.focal_px)
    depth = DepthMap(np.where(sphere.mask, zpx - np.nanmin(np.where(sphere.mask, zpx, np.nan)), 0.0), sphere.mask)
    s = ContinuousWave4(averaging_s=50.0).measure(sphere, _acq(), np.random.default_rng(1))
    _, _, fit = ItofFusion().metric_depth(depth, s, CAM)
    assert max(fit["offset_gains"]) < 0.5
    pts = s.points_m.copy()
    pts[0] *= (np.linalg.norm(pts[0]) + 0.03) / np.linalg.norm(pts[0])
    _, _, fit2 = ItofFusion().metric_depth(depth, ItofSample(pts, s.sigma_m), CAM)
    assert fit2["offset_gains"][0] > 0.8


def test_depth_noise_estimate():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:64, 0:64]
    smooth = 0.01 * (x - 32.0) ** 2 + 0.3 * y
    valid = np.ones((64, 64), bool)
    assert depth_noise(smooth, valid) < 0.02
    assert depth_noise(smooth + rng.normal(0, 0.5, smooth.shape), valid) == pytest.approx(0.5, rel=0.15)


def test_noise_free_fusion_barely_moves_points(sphere):
    """Adaptive diffusion (discrepancy principle): clean SFS keeps t small."""
    from nirspi_pipe.types import DepthMap

    zpx = sphere.depth_m / (0.2 / CAM.focal_px)
    depth = DepthMap(np.where(sphere.mask, zpx - np.nanmin(np.where(sphere.mask, zpx, np.nan)), 0.0), sphere.mask)
    s = ContinuousWave4(averaging_s=50.0).measure(sphere, _acq(), np.random.default_rng(1))
    clean = ItofFusion().fuse(depth, s, CAM)
    noisy = ItofFusion().fuse(degraded_depth(sphere, np.random.default_rng(0), noise_px=1.0), s, CAM)
    assert clean.info["time_step"] < 0.5 * noisy.info["time_step"]


# -- the voxel scales -------------------------------------------------------------------------------
def test_near_object_does_not_collapse():
    """A Ø100 mm sphere at 60 mm (issue 13): the fixed 5 mm voxel merged 7,576 points into 4."""
    scene = Sphere(distance_mm=60.0, diameter_mm=100.0, supersample=2).render(CAM)
    depth = degraded_depth(scene, np.random.default_rng(0))
    it = ContinuousWave4(averaging_s=50.0).aimed(Image2D(scene.radiance), CAM)
    cloud = ItofFusion().fuse(depth, it.measure(scene, _acq(), np.random.default_rng(0)), CAM)
    assert len(cloud.points_m) > 0.1 * cloud.info["pixels"]
    assert cloud.info["voxel_m"] < 2e-3
    assert len(PowerCrust().reconstruct(cloud).faces) > 100


def test_fixed_voxel_collapse_is_warned(sphere):
    depth = degraded_depth(sphere, np.random.default_rng(0))
    s = ContinuousWave4(averaging_s=50.0).measure(sphere, _acq(), np.random.default_rng(0))
    with pytest.warns(UserWarning, match="voxel merged"):
        ItofFusion(voxel_mm=20.0).fuse(depth, s, CAM)


# -- singular points --------------------------------------------------------------------------------
def _vase_field(n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic vase height field (pixels) and its Lambertian image, light at the viewer."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    x -= n / 2
    y -= (n - 1) / 2
    r = vase_profile(-y, 0.9 * n)
    h = np.sqrt(np.clip(r**2 - x**2, 0.0, None))
    dr = np.gradient(vase_profile(-y[:, 0], 0.9 * n), y[:, 0])[:, None]
    hs = np.where(h > 0, h, 1.0)
    gx, gy = -x / hs, r * dr / hs
    return h, np.where(h > 0, 1.0 / np.sqrt(1.0 + gx**2 + gy**2), 0.0)


def test_vase_singular_regions_get_consistent_depths():
    """The body's and the lip's ridges are singular at different heights: the maximal choice
    puts them apart (warned as ambiguous) and halves the error of "all at z = 0"."""
    h, img = _vase_field()
    errs = {}
    for choice in ("zero", "maximal"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            d = LaxFriedrichsSFS(scheme="second_order", singular=choice, source_tol=0.01, albedo=1.0).solve(
                Image2D(img), CAM
            )
        e = d.depth_m[d.mask] + h[d.mask]
        errs[choice] = float(np.mean(np.abs(e - np.median(e))))
        if choice == "maximal":
            assert d.info["singular_regions"] >= 2 and d.info["singular_regions_lifted"] >= 1
            assert any("ambiguous" in str(w.message) for w in caught)
    assert errs["maximal"] < 0.6 * errs["zero"]


def test_one_singular_region_is_unchanged(sphere):
    a = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(sphere.radiance), CAM)
    b = LaxFriedrichsSFS(scheme="godunov", singular="zero").solve(Image2D(sphere.radiance), CAM)
    assert np.array_equal(a.depth_m, b.depth_m)
    with pytest.raises(ConfigError, match="singular"):
        LaxFriedrichsSFS(singular="max")


# -- remeshing --------------------------------------------------------------------------------------
def test_remeshing_improves_skewness_and_keeps_the_surface(sphere):
    depth = degraded_depth(sphere, np.random.default_rng(0), noise_px=0.0, outlier_fraction=0.0)
    s = ContinuousWave4(averaging_s=50.0).measure(sphere, _acq(), np.random.default_rng(0))
    cloud = ItofFusion().fuse(depth, s, CAM)
    raw = PowerCrust(remesh_iterations=0).reconstruct(cloud)
    good = PowerCrust().reconstruct(cloud)
    sk_raw = equiangle_skewness(raw.vertices_m, raw.faces).mean()
    sk = equiangle_skewness(good.vertices_m, good.faces).mean()
    assert sk <= 0.30 < sk_raw
    centre, radius = np.array([0.0, 0.0, 0.2]), 0.025
    d_raw = np.abs(np.linalg.norm(raw.vertices_m - centre, axis=1) - radius)
    d = np.abs(np.linalg.norm(good.vertices_m - centre, axis=1) - radius)
    assert np.median(d) <= 1.1 * np.median(d_raw) + 5e-5


def test_remesh_small_or_empty_input_and_bad_keys():
    _, f, info = clean_and_remesh(np.zeros((0, 3)), np.zeros((0, 3), int), 1e-3)
    assert len(f) == 0 and info["faces_before_remesh"] == 0
    for key, value in [("remesh_iterations", -1), ("remesh_edge_factor", 0.0), ("max_hole_edges", 1.5)]:
        with pytest.raises(ConfigError, match=key):
            PowerCrust(**{key: value})


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["blobs", "noise", "nan", "const"]))
def test_aim_spots_hostile_images(seed, kind):
    """Spots land on pixels above the object threshold, or none with a note; never a crash."""
    rng = np.random.default_rng(seed)
    img = rng.random((32, 32))
    if kind == "blobs":
        from scipy import ndimage

        img = (ndimage.gaussian_filter(rng.random((32, 32)), 3) > 0.5).astype(float)
    elif kind == "nan":
        img[rng.random((32, 32)) < 0.3] = np.nan
    elif kind == "const":
        img = np.full((32, 32), float(rng.random()))
    px, notes = aim_spots(img, Camera(32), 4, 0.1)
    assert len(px) <= 4 and (len(px) > 0 or notes)
    assert np.all((px >= 0) & (px < 32))
    if kind == "blobs" and len(px):
        assert img[px[:, 0], px[:, 1]].all()
