"""Fusion itof, Alg. A3 (issue 44, item 2): precise anchors on an SFS shape with a few mm of
relative-depth error. The anchors' fit used to weigh them by their σ alone (10 µm with a
noiseless iToF), follow the shape error into a scale at its 1e-6 floor and, on multi, drop two
good anchors. With ``+fusion.shape_error=true`` it adds the SFS shape error ``τ`` (Paule–Mandel)
to every anchor's σ when the anchors disagree beyond their σ both with the fit and with any
positive scale and offset of their own (:func:`fit_with_shape_error`): an SFS depth of the wrong
scale but the right shape (the torus in the paper's fog chamber) keeps ``τ = 0``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.itof.cw4 import ContinuousWave4
from nirspi_pipe.mesh.anchors import _chi2_quantile, fit_anchors, fit_with_shape_error
from nirspi_pipe.mesh.fusion import ItofFusion
from nirspi_pipe.mesh.pointcloud import back_project
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Acquisition, Camera, DepthMap, ItofSample

PRIOR_MM = 200.0  # the default sphere's distance (the set-up's working distance)
ALPHA = ItofFusion().anchor_alpha  # 0.01: the level of the heterogeneity test
SCALE_PRIOR = ItofFusion().scale_prior_rel  # 0.2


@pytest.fixture(scope="module")
def sphere():
    """The default sphere at 64², its four iToF spots without an electronics floor (σ ≈ 10 µm:
    the spots' shot noise) and the pixel pitch at the spots' depth (the fusion's geometric
    scale, so a right fit has scale / pitch = 1)."""
    cam = Camera(64)
    scene = Sphere().render(cam)
    acq = Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1))
    itof = ContinuousWave4(ned_cm_per_sqrt_hz=0.0).measure(scene, acq, np.random.default_rng(0))
    assert float(np.max(itof.sigma_m)) < 2e-5
    pitch = float(np.mean(np.asarray(itof.points_m)[:, 2])) / cam.focal_px
    return scene, itof, pitch


def _sfs(scene, pitch: float, eta: np.ndarray) -> DepthMap:
    """Relative SFS depth of the sphere (pixel pitches, offset 30) plus the shape error ``eta``
    (pixel pitches)."""
    mask = scene.mask & np.isfinite(scene.depth_m)
    z = np.where(mask, scene.depth_m, 0.0)
    rel = (z - z[mask].min()) / pitch + 30.0 + eta
    return DepthMap(depth_m=np.where(mask, rel, np.nan), mask=mask, metric=False)


def _fuse(scene, depth: DepthMap, itof: ItofSample, shape_error: bool = True) -> tuple[float, dict]:
    """The fused depth's RMSE against the truth (mm) and the fit (``+fusion.shape_error=true``
    unless ``shape_error`` is False)."""
    fusion = ItofFusion(prior_distance_mm=PRIOR_MM, shape_error=shape_error)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zm, valid, fit = fusion.metric_depth(depth, itof, scene.camera)
    m = valid & scene.mask & np.isfinite(scene.depth_m)
    return float(np.sqrt(np.mean((zm[m] - scene.depth_m[m]) ** 2)) * 1e3), fit


#: Four anchor pixels on the sphere at different depths (175.0-178.7 mm), unlike the four
#: symmetric iToF spots, which all sit at one depth: there no anchor can tell a scale near 0 from
#: an SFS shape error (the anchors' own fit then explains them exactly with the scale at its floor).
ANCHOR_PX = ((20, 30), (31, 31), (40, 38), (27, 44))


def _pixel_anchors(scene, sigma: float, noise=(0.0, 0.0, 0.0, 0.0)) -> ItofSample:
    """Anchors on the true surface at :data:`ANCHOR_PX`, moved ``noise × sigma`` along their rays."""
    xyz = back_project(np.where(scene.mask, scene.depth_m, 0.0), scene.camera)
    pts = np.array([xyz[r, c] for r, c in ANCHOR_PX])
    rays = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    return ItofSample(pts + (sigma * np.asarray(noise))[:, None] * rays, np.full(4, sigma), {})


def _stepped(sphere):
    """The sphere whose SFS depth steps 5 pixel pitches behind from column 35 on, and four
    anchors at different depths exact to 10 µm."""
    scene, _, _ = sphere
    anchors = _pixel_anchors(scene, 1e-5)
    pitch = float(np.mean(np.asarray(anchors.points_m)[:, 2])) / scene.camera.focal_px
    cols = np.arange(64)[None, :] * np.ones((64, 1))
    return scene, _sfs(scene, pitch, 5.0 * (cols > 34.5)), anchors


def test_precise_anchors_on_a_stepped_sfs_shape(sphere):
    """SFS puts the sphere's right part 5 pixel pitches (about 5 mm) behind the rest (a region
    offset, as multi's separate SFS regions have); four anchors at different depths, exact to
    10 µm. With the shape error all four are kept, τ > 0, and the fused depth is 1 mm closer to
    the truth than without it (measured 3.48 against 4.75 mm; the scale 0.54 against 0.32 of the
    truth)."""
    scene, depth, anchors = _stepped(sphere)
    rmse_off, fit_off = _fuse(scene, depth, anchors, shape_error=False)
    rmse_on, fit_on = _fuse(scene, depth, anchors)
    assert fit_on["anchors_used"] == 4 and not fit_on["anchors_rejected"]
    assert rmse_on < rmse_off - 1.0, (rmse_on, rmse_off)
    assert fit_on["scale"] > fit_off["scale"] > 0
    assert fit_on["sfs_shape_error_m"] > 0 and fit_off["sfs_shape_error_m"] == 0.0


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    sfs_scale=st.floats(0.4, 2.5),
    log_sigma=st.floats(-5.0, np.log10(0.02)),
    noise=st.lists(st.floats(-1.5, 1.5), min_size=4, max_size=4),
)
def test_an_sfs_depth_of_another_scale_adds_no_shape_error(sphere, sfs_scale, log_sigma, noise):
    """SFS of the right shape but a scale 0.4-2.5 times the prior's (the torus in the paper's fog
    chamber: 0.48), anchors within 1.5 σ of the truth, σ from 10 µm to 2 cm: their χ² against
    their own best scale is at most 4 × 1.5² = 9, below the test's quantile (11.3 on 3 dof), so
    τ = 0 and the fit is bit for bit the one without the shape error, whatever the conflict with
    the scale prior (adding τ from the fit's χ² alone changed 36 of Table 3's 640 jobs, up to
    4.7 mm worse)."""
    scene, _, _ = sphere
    anchors = _pixel_anchors(scene, 10.0**log_sigma, noise)
    pitch = float(np.mean(np.asarray(anchors.points_m)[:, 2])) / scene.camera.focal_px
    depth = _sfs(scene, pitch * sfs_scale, np.zeros((64, 64)))
    _, fit_off = _fuse(scene, depth, anchors, shape_error=False)
    _, fit_on = _fuse(scene, depth, anchors)
    assert fit_on["sfs_shape_error_m"] == 0.0
    for key in ("scale", "offset_m", "placement_m", "chi2", "region_offsets_m", "anchors_used"):
        assert fit_on[key] == fit_off[key], key


def test_exact_shape_and_exact_anchors_add_no_shape_error(sphere):
    """No shape error: the anchors agree with SFS within their σ, no τ is added and the fit is
    the plain weighted fit (scale exact to 1e-3, depth within 0.05 mm)."""
    scene, itof, pitch = sphere
    rmse, fit = _fuse(scene, _sfs(scene, pitch, np.zeros((64, 64))), itof)
    assert fit["sfs_shape_error_m"] == 0.0 and fit["anchors_used"] == 4
    assert fit["scale"] / pitch == pytest.approx(1.0, abs=1e-3)
    assert rmse < 0.05


def _fit_on(zr: np.ndarray, z: np.ndarray):
    def fit(sig: np.ndarray):
        return fit_anchors(zr, z, sig, float(np.mean(zr)), 180.0, SCALE_PRIOR, 0.2, 0.05)

    return fit


@settings(max_examples=60, deadline=None)
@given(
    zr=st.lists(st.floats(-20.0, 20.0), min_size=2, max_size=6),
    shape_mm=st.lists(st.floats(-10.0, 10.0), min_size=6, max_size=6),
    log_sigma=st.floats(-6.0, np.log10(0.02)),
    true_scale=st.floats(0.5, 1.5),
)
def test_the_shape_error_is_the_paule_mandel_root(zr, shape_mm, log_sigma, true_scale):
    """Anchors on a relative depth ``zr`` with a shape error of up to 1 cm and σ from 1 µm to
    2 cm: ``τ = 0`` (the plain fit, unchanged) when the fit's χ² is within its quantile; otherwise
    the refit's χ² is at most its dof, and 1 % less ``τ`` leaves it above (the root, to the
    solver's tolerance); the scale is positive and within 1 ± scale_prior_rel·sqrt(dof)."""
    zr_a = np.asarray(zr)
    z = 0.2 + true_scale * 0.2 / 180.0 * (zr_a - zr_a.mean()) + 1e-3 * np.asarray(shape_mm[: len(zr)])
    sig = np.full(len(zr), 10.0**log_sigma)
    fit = _fit_on(zr_a, z)
    plain = fit(sig)
    got = fit_with_shape_error(fit, sig, ALPHA)
    assert got.scale > 0
    if plain.chi2 <= _chi2_quantile(ALPHA, plain.dof):
        assert got.shape_error_m == 0.0 and got.scale == plain.scale and got.chi2 == plain.chi2
        return
    tau = got.shape_error_m
    assert tau > 0 and got.chi2 <= got.dof * (1 + 1e-9)
    below = fit(np.sqrt(sig**2 + (tau * (1 - 1e-2)) ** 2))
    assert below.chi2 > got.dof
    assert abs(got.scale / got.scale_ref - 1.0) <= SCALE_PRIOR * np.sqrt(got.dof) * (1 + 1e-6)


def test_the_shape_error_is_off_by_default(sphere):
    """Off by default (the paper's Table 3/4 jobs keep their numbers): the stepped shape with
    precise anchors then fits without it, as before b1cceda, and records 0; on, it is added."""
    assert ItofFusion().shape_error is False
    scene, depth, anchors = _stepped(sphere)
    _rmse_off, fit_off = _fuse(scene, depth, anchors, shape_error=False)
    _rmse_on, fit_on = _fuse(scene, depth, anchors)
    assert fit_off["sfs_shape_error_m"] == 0.0 and fit_on["sfs_shape_error_m"] > 0
