"""Fusion itof, Alg. A3 (issue 44, item 2): precise anchors on an SFS shape with a few mm of
relative-depth error. The anchors' fit used to weigh them by their σ alone (10 µm with a
noiseless iToF), follow the shape error into a scale at its 1e-6 floor and, on multi, drop two
good anchors; it now adds the SFS shape error ``τ`` (Paule–Mandel) to every anchor's σ when
the anchors disagree with the SFS shape beyond their σ (:func:`fit_with_shape_error`)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.itof.cw4 import ContinuousWave4
from nirspi_pipe.mesh.anchors import _chi2_quantile, fit_anchors, fit_with_shape_error
from nirspi_pipe.mesh.fusion import ItofFusion
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


def test_precise_anchors_on_a_stepped_sfs_shape_keep_the_scale(sphere):
    """SFS puts the right half of the sphere 10 pixel pitches (about 10 mm) behind the left (a
    region offset, as multi's separate SFS regions have), the four spots are exact to 10 µm. All
    four anchors are kept; the scale stays within 1 ± scale_prior_rel·sqrt(dof) of the truth (the
    Paule–Mandel bound, dof = 4 anchors + 2 priors − 2; measured 0.85); the fused depth is within
    2 mm RMS of the truth (measured 1.47 mm: the local offsets take the step). The fit with the
    anchors' σ alone drove the scale to 7e-4 of the truth and scored 6.65 mm."""
    scene, itof, pitch = sphere
    cols = np.arange(64)[None, :] * np.ones((64, 1))
    rmse, fit = _fuse(scene, _sfs(scene, pitch, 10.0 * (cols > 31.5)), itof)
    assert fit["anchors_used"] == 4 and not fit["anchors_rejected"]
    assert abs(fit["scale"] / pitch - 1.0) <= SCALE_PRIOR * 2.0
    assert rmse < 2.0
    assert fit["sfs_shape_error_m"] > 1e-3  # the step's share at the spots, metres
    assert fit["worse_than_sfs"] is False


def test_exact_shape_and_exact_anchors_add_no_shape_error(sphere):
    """No shape error: the anchors agree with SFS within their σ, no τ is added and the fit is
    the plain weighted fit (scale exact to 1e-3, depth within 0.05 mm)."""
    scene, itof, pitch = sphere
    rmse, fit = _fuse(scene, _sfs(scene, pitch, np.zeros((64, 64))), itof)
    assert fit["sfs_shape_error_m"] == 0.0 and fit["anchors_used"] == 4
    assert fit["scale"] / pitch == pytest.approx(1.0, abs=1e-3)
    assert rmse < 0.05


#: Issue 44's σ range: a noiseless iToF (the fixture's 10 µm) up to 2 cm (twice the default's 1 cm).
SIGMAS_M = (1e-5, 1e-3, 2.2e-3, 4.7e-3, 1e-2, 2e-2)
#: How much the fused depth error at σ = 10 µm may exceed the best over the larger σ (mm): the
#: worst of 80 random shapes of this strategy was 1.68 mm (a 0.1-pitch step whose χ² stays just
#: under the test's quantile, so no τ is added and the plain fit moves the scale 43 %). The fit with
#: the anchors' σ alone exceeded it by 0.87-5.8 mm (median 4.8 mm) on 20 of them.
GROWTH_TOL_MM = 2.5


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    amp=st.floats(0.0, 10.0),
    step=st.booleans(),
    fx=st.floats(10.0, 80.0),
    fy=st.floats(10.0, 80.0),
    phase=st.floats(0.0, 6.28),
    noise=st.lists(st.floats(-2.5, 2.5), min_size=4, max_size=4),
)
def test_cleaner_anchors_do_not_make_the_fit_worse(sphere, amp, step, fx, fy, phase, noise):
    """A smooth or stepped SFS shape error of 0-10 pixel pitches, and the same standardised noise
    draw at σ from 10 µm to 2 cm along each spot's ray: the scale ratio to its prior stays within
    1 ± scale_prior_rel·sqrt(q) (q the χ² quantile at 1 − anchor_alpha on the fit's dof: a bound
    that holds with and without τ), and shrinking σ to 10 µm costs at most GROWTH_TOL_MM over the
    best σ."""
    scene, itof, pitch = sphere
    rows, cols = np.mgrid[0:64, 0:64].astype(np.float64)
    if step:
        eta = amp * (((cols - 31.5) * np.cos(phase) + (rows - 31.5) * np.sin(phase)) > 3.0 * np.sin(3 * phase))
    else:
        eta = amp * np.cos(np.pi * (cols - 31.5) / fx + phase) * np.sin(np.pi * (rows - 31.5) / fy)
    depth = _sfs(scene, pitch, eta)
    pts0 = np.asarray(itof.points_m, dtype=np.float64)
    rays = pts0 / np.linalg.norm(pts0, axis=1, keepdims=True)
    errors = []
    for sig in SIGMAS_M:
        pts = pts0 + (sig * np.asarray(noise))[:, None] * rays
        rmse, fit = _fuse(scene, depth, ItofSample(pts, np.full(4, sig), dict(itof.info)))
        bound = SCALE_PRIOR * np.sqrt(_chi2_quantile(ALPHA, fit["anchors_used"]))
        assert abs(fit["scale"] / fit["scale_prior"] - 1.0) <= bound * (1 + 1e-6), (sig, fit["scale"])
        errors.append(rmse)
    assert errors[0] <= min(errors[1:]) + GROWTH_TOL_MM, errors


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
    scene, itof, pitch = sphere
    cols = np.arange(64)[None, :] * np.ones((64, 1))
    depth = _sfs(scene, pitch, 10.0 * (cols > 31.5))
    _rmse_off, fit_off = _fuse(scene, depth, itof, shape_error=False)
    _rmse_on, fit_on = _fuse(scene, depth, itof)
    assert fit_off["sfs_shape_error_m"] == 0.0 and fit_on["sfs_shape_error_m"] > 1e-3
