"""iToF cw4: demodulation, ambiguity, noise, fog, misses and configuration errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.itof.cw4 import C_M_S, ContinuousWave4, ambiguity_range_m, demodulate_4phase, laser_directions
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Acquisition, Camera, Medium

F = 4.8e6


def _acq(**medium: float) -> Acquisition:
    return Acquisition(n=64, indices=np.arange(1), y_pos=np.zeros(1), medium=Medium(**medium))


@pytest.fixture(scope="module")
def sphere():
    return Sphere().render(Camera(64))


def _samples(phi: float, amp: float = 100.0, offset: float = 400.0) -> np.ndarray:
    return offset / 4 + amp / 2 * np.cos(phi + np.pi / 2 * np.arange(4))


def test_phase_to_distance_exact():
    r = 1.234
    phi = 4 * np.pi * F * r / C_M_S
    d, a, s = demodulate_4phase(_samples(phi), F)
    assert d == pytest.approx(r, rel=1e-12)
    assert a == pytest.approx(50.0) and s == pytest.approx(400.0)


def test_ambiguity_wrap():
    lam = ambiguity_range_m(F)
    assert lam == pytest.approx(31.228, abs=1e-3)
    r = lam + 2.0
    d, _, _ = demodulate_4phase(_samples(4 * np.pi * F * r / C_M_S), F)
    assert d == pytest.approx(2.0, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    r=st.floats(0.0, 100.0),
    amp=st.floats(1e-6, 1e9),
    offset_factor=st.floats(1.0, 1e3),
)
def test_demodulation_any_range(r, amp, offset_factor):
    phi = 4 * np.pi * F * r / C_M_S
    d, a, _ = demodulate_4phase(_samples(phi, amp, 2 * amp * offset_factor), F)
    lam = ambiguity_range_m(F)
    assert np.isfinite(d) and 0.0 <= d < lam
    err = abs(d - r % lam)
    assert min(err, lam - err) < 1e-6 * lam
    assert a == pytest.approx(amp / 2, rel=1e-6)


def test_zero_signal_demodulation_is_finite():
    d, a, s = demodulate_4phase(np.zeros(4), F)
    assert d == 0.0 and a == 0.0 and s == 0.0


def test_directions_at_90_degrees():
    d = laser_directions(3.5, 45.0)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    lateral = d[:, :2] / np.linalg.norm(d[:, :2], axis=1, keepdims=True)
    assert np.allclose(lateral @ lateral.T, [[1, 0, -1, 0], [0, 1, 0, -1], [-1, 0, 1, 0], [0, -1, 0, 1]], atol=1e-12)
    assert np.allclose(np.degrees(np.arccos(d[:, 2])), 3.5)


def test_defaults_follow_table1():
    it = ContinuousWave4()
    assert it.f_mod_hz == 4.8e6 and it.t_int_us == 150.0 and it.ned_cm_per_sqrt_hz == 1.0
    assert it.sigma_floor_m == pytest.approx(0.01)  # Table 1 sigma_min = 1 cm


def test_measured_points_within_sigma(sphere):
    it = ContinuousWave4()
    rng = np.random.default_rng(3)
    dirs = laser_directions(it.spot_angle_deg, it.azimuth_deg)
    # true ranges by ray casting the sphere analytically
    c, rad = np.array([0, 0, 0.2]), 0.025
    b = dirs @ c
    true_r = b - np.sqrt(b * b - (c @ c - rad * rad))
    errs = []
    for _ in range(40):
        s = it.measure(sphere, _acq(), rng)
        r = np.linalg.norm(s.points_m, axis=1)
        assert np.allclose(s.points_m / r[:, None], dirs)
        errs.append((r - true_r) / s.sigma_m)
    errs = np.concatenate(errs)
    assert abs(errs.mean()) < 0.5  # unbiased within the pixel interpolation error
    assert 0.7 < errs.std() < 1.3  # sigma is the real spread


def test_fog_and_background_increase_sigma(sphere):
    it = ContinuousWave4(averaging_s=50.0)  # floor 1 mm: shot noise visible
    rng = np.random.default_rng(0)
    clear = it.measure(sphere, _acq(background_irradiance_w_m2=100.0), rng)
    foggy = it.measure(sphere, _acq(beta_per_m=10.0, background_irradiance_w_m2=100.0), rng)
    assert np.all(foggy.sigma_m > clear.sigma_m)
    assert foggy.info["signal_electrons_mean"] < clear.info["signal_electrons_mean"] * np.exp(-2 * 10 * 0.17)
    dark = it.measure(sphere, _acq(), rng)
    assert np.all(dark.sigma_m <= clear.sigma_m)


def test_spot_missing_object_warns_and_sigma_inf():
    scene = Sphere(diameter_mm=10.0).render(Camera(64))
    with pytest.warns(UserWarning, match="no valid return"):
        s = ContinuousWave4(spot_angle_deg=6.0).measure(scene, _acq(), np.random.default_rng(0))
    assert np.all(np.isinf(s.sigma_m)) and np.all(np.isfinite(s.points_m))
    assert s.info["valid_spots"] == 0
    # no valid return: no sigma to record (absent, never inf in the record)
    assert "sigma_mean_m" not in s.info
    assert all(np.isfinite(v) for v in s.info.values() if isinstance(v, float))


def test_spot_outside_view_is_config_error(sphere):
    with pytest.raises(ConfigError, match="spot_angle_deg"):
        ContinuousWave4(spot_angle_deg=30.0).measure(sphere, _acq(), np.random.default_rng(0))


def test_needs_scene():
    with pytest.raises(NirspiError):
        ContinuousWave4().measure(None, _acq(), np.random.default_rng(0))


@pytest.mark.parametrize(
    "key,value",
    [
        ("f_mod_mhz", 0.0),
        ("t_int_us", -1.0),
        ("averaging_s", 1e-6),
        ("spot_angle_deg", 90.0),
        ("quantum_efficiency", 1.5),
        ("demod_contrast", 0.0),
        ("ned_cm_per_sqrt_hz", float("nan")),
        ("laser_power_mw", 1.1e15),
    ],
)
def test_bad_config(key, value):
    with pytest.raises(ConfigError, match=key):
        ContinuousWave4(**{key: value})


def test_extreme_fog_is_flagged_not_nan(sphere):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = ContinuousWave4().measure(
            sphere, _acq(beta_per_m=200.0, background_irradiance_w_m2=1e3), np.random.default_rng(0)
        )
    assert not np.any(np.isnan(s.points_m)) and not np.any(np.isnan(s.sigma_m))
    assert np.all(np.isinf(s.sigma_m)) and caught


@settings(max_examples=25, deadline=None)
@given(log_power_mw=st.floats(8.0, 15.0), seed=st.integers(0, 2**16))
def test_huge_signal_has_a_gaussian_shot_noise(sphere, log_power_mw, seed):
    """Laser powers up to 1e15 mW, the largest allowed (counts far beyond numpy's Poisson limit, ~9e18, which raised
    `ValueError: lam value too large`; e.g. itof.laser_power_mw=1e12, or a sphere almost touching
    the lens): the shot noise falls back to a Gaussian of the same mean and variance, as the
    photodiode's does, and every spot is finite, valid and within 5 sigma of the truth."""
    it = ContinuousWave4(laser_power_mw=10.0**log_power_mw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning either
        s = it.measure(sphere, _acq(), np.random.default_rng(seed))
    dirs = laser_directions(it.spot_angle_deg, it.azimuth_deg)
    c, rad = np.array([0, 0, 0.2]), 0.025
    b = dirs @ c
    true_r = b - np.sqrt(b * b - (c @ c - rad * rad))
    assert np.all(np.isfinite(s.points_m)) and np.all(np.isfinite(s.sigma_m)) and s.info["valid_spots"] == 4
    assert np.all(np.abs(np.linalg.norm(s.points_m, axis=1) - true_r) < 5 * s.sigma_m + 1e-4)


def test_shot_noise_switch_keeps_the_variance():
    """Above 1e7 electrons the counts are Gaussian with the Poisson variance (mean = variance)."""
    from nirspi_pipe.physics.detector import sample_electrons

    mean = np.full(20000, 1e20)
    x = sample_electrons(mean, np.random.default_rng(0), shot=True, read_noise_e=0.0)
    assert np.var(x) / 1e20 == pytest.approx(1.0, rel=0.05) and abs(np.mean(x) / 1e20 - 1) < 1e-9
