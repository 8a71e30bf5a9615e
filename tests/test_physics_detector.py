"""Detector: shot, dark and read noise, pedestal, saturation and ADC; time-varying factors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.detector import Photodiode, digitize, sample_electrons
from nirspi_pipe.physics.timevarying import background_factor, fog_factor, ornstein_uhlenbeck


def test_shot_and_read_noise_statistics():
    rng = np.random.default_rng(0)
    e = sample_electrons(np.full(200000, 1000.0), rng, shot=True, read_noise_e=30.0)
    assert e.mean() == pytest.approx(1000.0, abs=1.0)
    assert e.var() == pytest.approx(1000.0 + 900.0, rel=0.03)
    big = sample_electrons(np.full(20000, 1e9), rng, shot=True, read_noise_e=0.0)  # Gaussian branch
    assert big.std() == pytest.approx(np.sqrt(1e9), rel=0.05)
    assert np.array_equal(sample_electrons(np.array([5.0]), rng, shot=False, read_noise_e=0.0), [5.0])


def test_digitize_counts_saturation_and_quantises():
    counts, sat, step = digitize(np.array([-5.0, 0.0, 10.0, 99.0, 100.0, 1e12]), 100.0, 4)
    assert step == pytest.approx(100 / 16)
    assert sat.tolist() == [False, False, False, False, True, True]
    assert counts.min() == 0 and counts.max() == 15
    assert counts[2] == 1  # 10 e⁻ / 6.25 e⁻ per count


def test_photodiode_full_scale_from_c_eq_and_expected_noise():
    d = Photodiode()
    assert d.full_scale_e == pytest.approx(19e-15 / 1.602176634e-19)
    assert d.dark_electrons == pytest.approx(0.0066e-9 * 150e-6 / 1.602176634e-19)
    n = d.noise_e(1e4)
    assert n == pytest.approx(np.sqrt(d.read_noise_e**2 + 1e4 + d.dark_electrons + d.electrons_per_count**2 / 12))
    rng = np.random.default_rng(1)
    counts, _ = d.read(np.full(50000, 1e4), rng)
    assert np.std(counts) * d.electrons_per_count == pytest.approx(n, rel=0.03)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"read_noise_e": -1.0}, "read_noise_e"),
        ({"adc_bits": 0}, "adc_bits"),
        ({"full_scale_v": -1.0}, "full_scale_v"),
        ({"budget": {"f_number": -2}}, "budget.f_number"),
    ],
)
def test_impossible_detector_inputs_name_the_key(kwargs, key):
    with pytest.raises(ConfigError) as err:
        Photodiode(**kwargs)
    assert err.value.key == key


@settings(max_examples=50, deadline=None)
@given(
    mean=st.one_of(st.just(0.0), st.floats(0.0, 1e30)),
    bits=st.sampled_from([None, 8, 16]),
    fs=st.sampled_from([None, 1.0, 5.0]),
)
def test_readings_stay_finite_and_in_range(mean, bits, fs):
    d = Photodiode(adc_bits=bits, full_scale_v=fs)
    counts, sat = d.read(np.full(8, mean), np.random.default_rng(0))
    assert np.isfinite(counts).all() and (counts >= 0).all()
    if fs is not None and bits is not None:
        assert (counts <= 2**bits - 1).all()
    if fs is not None and mean > 10 * d.full_scale_e:
        assert sat.all()


def test_ornstein_uhlenbeck_statistics_and_seeding():
    t = np.arange(100000) * 1e-3
    x = ornstein_uhlenbeck(t, 0.2, 0.01, np.random.default_rng(3))
    assert x.std() == pytest.approx(0.2, rel=0.05)
    assert np.corrcoef(x[:-10], x[10:])[0, 1] == pytest.approx(np.exp(-1.0), abs=0.03)
    assert np.array_equal(x, ornstein_uhlenbeck(t, 0.2, 0.01, np.random.default_rng(3)))
    uneven = np.sort(np.random.default_rng(0).uniform(0, 10, 20000))
    assert ornstein_uhlenbeck(uneven, 0.2, 0.05, np.random.default_rng(1)).std() == pytest.approx(0.2, rel=0.1)
    assert not ornstein_uhlenbeck(t, 0.0, 0.01, np.random.default_rng(3)).any()


def test_time_factors_are_non_negative():
    t = np.linspace(0, 10, 1000)
    rng = np.random.default_rng(0)
    f = background_factor(t, rng, drift_rel_per_s=-1.0, flicker_rel=2.0, flicker_hz=50.0, wander_rel=1.0)
    assert (f >= 0).all() and np.isfinite(f).all()
    assert (fog_factor(t, rng, 1.0, 0.1) >= 0).all()
    assert np.allclose(background_factor(t, rng), 1.0)
