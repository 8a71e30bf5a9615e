"""Fusion itof, Alg. A3's anchors (issue 40 item 4, issue 44): weighted by their stated noise,
tested for consistency (chi-square), a scale that never turns negative, anchors whose noise makes
them useless leave the depth where the working-distance prior puts it, and a fused result the fit
expects to be worse than SFS alone is flagged."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.itof.cw4 import ContinuousWave4
from nirspi_pipe.mesh.anchors import fit_anchors, worse_than_prior
from nirspi_pipe.mesh.fusion import ItofFusion
from nirspi_pipe.mesh.pointcloud import semi_even_points
from nirspi_pipe.mesh.standin import degraded_depth
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Acquisition, Camera, ItofSample

PRIOR_MM = 200.0  # the default sphere's distance (the set-up's working distance)


@pytest.fixture(scope="module")
def scene():
    return Sphere().render(Camera(64))


@pytest.fixture(scope="module")
def depth(scene):
    return degraded_depth(scene, np.random.default_rng(0))


@pytest.fixture(scope="module")
def itof(scene):
    acq = Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1))
    return ContinuousWave4().measure(scene, acq, np.random.default_rng(0))


def _with(itof: ItofSample, points: np.ndarray, sigma: np.ndarray, info: bool = True) -> ItofSample:
    return ItofSample(points_m=points, sigma_m=sigma, info=dict(itof.info) if info else {})


@settings(max_examples=80, deadline=None)
@given(
    zr=st.lists(st.floats(-50, 50), min_size=1, max_size=6),
    z=st.lists(st.floats(1e-3, 30.0), min_size=6, max_size=6),
    log_sigma=st.floats(-6, 9),
    prior=st.sampled_from([None, 0.2]),
    rel=st.sampled_from([None, 0.2, 1.0]),
)
def test_scale_is_positive_by_construction(zr, z, log_sigma, prior, rel):
    """Any anchors, including ones that ask for an inverted SFS depth (depth falling where SFS
    rises): the fitted scale is finite and > 0 (the fit is in log scale), or the anchors are
    refused in one line when they cannot fix the scale."""
    zr_a = np.asarray(zr)
    z_a = np.asarray(z[: len(zr)])
    sig = np.full(len(zr), 10.0**log_sigma)
    try:
        fit = fit_anchors(zr_a, z_a, sig, float(np.median(zr_a)), 180.0, rel, prior, 0.05 if prior else None)
    except NirspiError as e:
        assert rel is None and ("scale" in str(e))
        return
    assert np.isfinite(fit.scale) and fit.scale > 0
    assert np.isfinite(fit.offset_m) and fit.placement_m > 0 and np.isfinite(fit.placement_sigma_m)
    assert fit.chi2 >= 0 and np.isfinite(fit.chi2)


def test_inverted_anchors_do_not_flip_the_scale():
    """Anchors that say the depth falls where SFS rises, exactly (the old linear fit returned a
    negative scale with a warning; issue 44): the scale stays positive, pulled to its floor."""
    zr = np.array([-10.0, -5.0, 5.0, 10.0])
    z = 0.2 - 1.1e-3 * zr  # s = -1.1 mm per unit: the geometric scale with its sign flipped
    fit = fit_anchors(zr, z, np.full(4, 1e-4), 0.0, 180.0, 0.2, 0.2, 0.05)
    assert fit.scale > 0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    log_sigma=st.floats(3.0, 9.0),
    z=st.lists(st.floats(1e-3, 31.0), min_size=4, max_size=4),
    info=st.booleans(),
)
def test_useless_anchors_leave_the_prior(scene, depth, itof, log_sigma, z, info):
    """Anchors with sigma >= 1 km (itof.ned_cm_per_sqrt_hz=1e9 gives 1e7 m), anywhere in the
    iToF's range: the depth is placed by the working-distance prior (the median SFS pixel at
    200 mm within 1 µm), no local offset moves it, a warning says so, and the record holds no
    flag (the fused depth is then the prior's, not worse)."""
    pts = np.asarray(itof.points_m)
    dirs = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    wild = dirs * np.asarray(z)[:, None] / dirs[:, 2:3]
    bad = _with(itof, wild, np.full(4, 10.0**log_sigma), info=info)
    fusion = ItofFusion(prior_distance_mm=PRIOR_MM)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        zm, valid, fit = fusion.metric_depth(depth, bad, scene.camera)
    assert abs(fit["placement_m"] - PRIOR_MM * 1e-3) < 1e-6
    assert float(np.median(zm[valid])) == pytest.approx(PRIOR_MM * 1e-3, abs=5e-3)  # despiked median
    assert fit["region_offsets_m"] == [0.0] * 4 and fit["worse_than_sfs"] is False
    assert fit["anchor_share"] < 1e-6
    assert any("prior" in str(w.message) for w in caught)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    which=st.integers(0, 3),
    sigmas_off=st.floats(20.0, 2000.0),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_one_wild_anchor_is_rejected(scene, depth, itof, which, sigmas_off, sign):
    """One anchor 20 to 2000 of its sigma off along its ray (a multipath return, a wrapped
    phase): the chi-square test rejects it and lists why; the other three are kept, and the
    placement is where the three put it (within 4 of their combined sigma)."""
    pts = np.array(itof.points_m, dtype=np.float64)
    sig = np.asarray(itof.sigma_m, dtype=np.float64)
    fusion = ItofFusion(prior_distance_mm=PRIOR_MM)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, good = fusion.metric_depth(depth, itof, scene.camera)
    d = pts[which] / np.linalg.norm(pts[which])
    pts[which] = pts[which] + sign * sigmas_off * sig[which] * d
    if pts[which][2] <= 0:
        return
    with pytest.warns(UserWarning, match="inconsistent"):
        _, _, fit = fusion.metric_depth(depth, _with(itof, pts, sig), scene.camera)
    assert set(fit["anchors_rejected"]) == {str(which)}
    assert "inconsistent" in fit["anchors_rejected"][str(which)]
    assert fit["anchors_used"] == 3
    assert abs(fit["placement_m"] - good["placement_m"]) < 4 * float(np.max(sig)) / np.sqrt(3)


def test_anchors_within_their_noise_are_all_kept(scene, depth):
    """Ten noise draws of the default iToF (sigma 1 cm): no anchor is rejected, the fit's chi2
    p-value is recorded, and nothing is flagged."""
    acq = Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1))
    fusion = ItofFusion(prior_distance_mm=PRIOR_MM)
    for seed in range(10):
        it = ContinuousWave4().measure(scene, acq, np.random.default_rng(seed))
        _, _, fit = fusion.metric_depth(depth, it, scene.camera)
        assert fit["anchors_used"] == 4, (seed, fit["anchors_rejected"])
        assert 0.0 <= fit["chi2_p"] <= 1.0 and fit["worse_than_sfs"] is False
        assert fit["anchor_share"] > 0.95  # four 1 cm anchors against a 50 mm prior


def test_flag_when_anchors_scatter_beyond_their_noise():
    """worse_than_prior: anchors whose chi2 says they scatter R times their sigma are flagged
    exactly when R^2 > 2 + sigma_p^2/sigma_a^2 (the placement's mean square error exceeds the
    prior's); consistent anchors never are."""
    zr = np.array([-5.0, -2.0, 2.0, 5.0])
    base = 0.2 + 0.2 / 180.0 * zr
    for scatter, flagged in ((1.0, False), (3.0, True)):
        # sigma 1 m against a 50 mm prior: sigma_a = 0.5 m, the limit is R > sqrt(2.01)
        z = base + scatter * np.array([1.0, -1.0, 1.0, -1.0])
        fit = fit_anchors(zr, z, np.full(4, 1.0), 0.0, 180.0, 0.2, 0.2, 0.05)
        assert (worse_than_prior(fit, 0.05, 4, True) is not None) is flagged, scatter
    z = base + 0.5 * np.array([1.0, -1.0, 1.0, -1.0])
    assert worse_than_prior(fit_anchors(zr, z, np.full(4, 1.0), 0.0, 180.0, 0.2, 0.2, 0.05), 0.05, 4, True) is None
    assert worse_than_prior(fit_anchors(zr, z, np.full(4, 1.0), 0.0, 180.0, 0.2), None, 4, True) is None


def test_majority_rejected_is_flagged(scene, depth, itof):
    """Two anchors moved far the same way: the test rejects anchors until the rest agree; with
    as many rejected as kept the record says why the fused depth is not trusted."""
    pts = np.array(itof.points_m, dtype=np.float64)
    sig = np.asarray(itof.sigma_m, dtype=np.float64)
    for k, step in ((2, 0.5), (3, 1.0)):
        pts[k] = pts[k] * (1 + step / np.linalg.norm(pts[k]))
    fusion = ItofFusion(prior_distance_mm=PRIOR_MM)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _, _, fit = fusion.metric_depth(depth, _with(itof, pts, sig), scene.camera)
    assert len(fit["anchors_rejected"]) == 2
    assert fit["worse_than_sfs"] is True and "rejected 2 of 4" in fit["worse_than_sfs_reason"]
    assert any("flagged worse than SFS alone" in str(w.message) for w in caught)


def test_too_many_points_is_a_data_error_naming_the_span():
    """Alg. A4's guard: a surface far larger than the pitch is a property of the data (a failed
    job naming the span and the count), not a config error blaming fusion.d_pitch_mm."""
    tri = np.array([[[0.0, 0.0, 1.0], [30.0, 0.0, 1.0], [0.0, 30.0, 1.0]]])
    with pytest.raises(NirspiError, match=r"spans 42.4 m .* would need \d+ points") as err:
        semi_even_points(tri, tri[:, 0], 5e-3)
    assert "is not allowed" not in str(err.value) and "fusion.d_pitch_mm" in str(err.value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    k=st.integers(1, 7),
    seed=st.integers(0, 2**16),
    noise=st.sampled_from([1e-4, 1e-2, 0.1]),
    scale_prior=st.sampled_from([None, 0.2]),
    prior=st.booleans(),
)
def test_the_blas_free_fit_reaches_the_minimum_a_reference_optimiser_finds(k, seed, noise, scale_prior, prior):
    """The anchors' fit is a hand-written Levenberg–Marquardt (no BLAS/LAPACK, so its bits do not
    depend on the kernel set: docs/sweeps.md). Its objective at the solution is never above what
    scipy's trust-region least_squares reaches from the same start (up to 1e-9 relative), and the
    scale is positive."""
    from scipy.optimize import least_squares

    if scale_prior is None and k < 2:
        return
    rng = np.random.default_rng(seed)
    zr = rng.normal(0.0, 20.0, k)
    z = 0.3 + 0.3 / 180.0 * zr * rng.uniform(0.5, 1.5) + rng.normal(0.0, noise, k)
    sig = np.full(k, noise)
    ref = float(np.mean(zr))
    fit = fit_anchors(zr, z, sig, ref, 180.0, scale_prior, 0.3 if prior else None, 0.075 if prior else None)
    assert fit.scale > 0
    b = zr - ref

    def res(x):
        c = np.exp(x[1])
        s = np.exp(x[0]) * c / 180.0
        out = [(c + s * b - z) / sig]
        if scale_prior is not None:
            out.append([np.expm1(x[0]) / scale_prior])
        if prior:
            out.append([(c - 0.3) / 0.075])
        return np.concatenate(out)

    bound = np.log(1e6)
    sol = least_squares(
        res, [0.0, np.log(0.3)], bounds=([-bound, -np.inf], [bound, np.log(1e12)]), xtol=1e-12, ftol=1e-12, gtol=1e-12
    )
    ours = fit.chi2
    assert ours <= float(np.sum(sol.fun**2)) * (1 + 1e-9) + 1e-20
