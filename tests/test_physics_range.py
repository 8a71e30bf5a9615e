"""Range model (Alg. A1), its calibration on Table 2, and the theory rows."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics import range_model as rm
from nirspi_pipe.physics.detector import Photodiode
from nirspi_pipe.physics.fog import MieFog
from nirspi_pipe.physics.range_model import calibrate, max_distance_m, paper_table2, snr


@pytest.fixture(scope="module")
def cal():
    return calibrate()


def test_config_defaults_are_the_calibration(cal):
    # What a run uses: the composed config (the classes' defaults, through the option schemas).
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["detector=ingaas", "fog=chamber"])
    det, fog = cfg.detector, cfg.fog
    assert det["read_noise_e"] == pytest.approx(cal["read_noise_e"], rel=1e-3)
    assert fog["number_density_per_cm3"] == pytest.approx(cal["number_density_per_cm3"], rel=1e-3)
    assert Photodiode().read_noise_e == pytest.approx(det["read_noise_e"])
    assert MieFog().number_density_per_cm3 == pytest.approx(fog["number_density_per_cm3"])
    assert MieFog().extinction_per_m == pytest.approx(cal["beta_per_m"], rel=1e-3)


def test_theory_rows_within_5_percent_of_the_paper():
    paper = paper_table2()
    det, fog = Photodiode(), MieFog()
    cond = {"beta_per_m": fog.extinction_per_m, "backscatter_gain": fog.backscatter_gain, "fog_extent_m": fog.extent_m}
    for refl in (0.2, 0.5, 0.8):
        assert max_distance_m(refl, det) == pytest.approx(paper["theory_no_fog"][refl], rel=0.05)
        assert max_distance_m(refl, det, **cond) == pytest.approx(paper["theory_fog"][refl], rel=0.05)


def test_no_fog_range_scales_as_sqrt_reflectance():
    det = Photodiode()
    z = [max_distance_m(r, det) for r in (0.2, 0.5, 0.8)]
    assert z[1] / z[0] == pytest.approx(np.sqrt(0.5 / 0.2), rel=1e-6)
    assert z[2] / z[0] == pytest.approx(np.sqrt(0.8 / 0.2), rel=1e-6)


def test_fog_range_solves_z_exp_beta_z():
    det = Photodiode()
    z0 = max_distance_m(0.5, det)
    for beta in (0.5, 2.0, 8.0):
        z = max_distance_m(0.5, det, beta_per_m=beta)
        assert z * np.exp(beta * z) == pytest.approx(z0, rel=1e-6)


def test_snr_meets_threshold_at_max_distance():
    det = Photodiode()
    z = max_distance_m(0.3, det, beta_per_m=1.0, photon_irradiance=1e19)
    assert snr(z, 0.3, det, beta_per_m=1.0, photon_irradiance=1e19) == pytest.approx(1.0, rel=1e-6)


def test_background_light_shortens_the_range():
    det = Photodiode()
    from nirspi_pipe.physics.light import Background

    zs = [
        max_distance_m(0.5, det, photon_irradiance=Background(klux=k).photon_irradiance)
        for k in (0.0, 15.0, 50.0, 100.0)
    ]
    assert all(a > b for a, b in zip(zs, zs[1:]))


def test_impossible_range_inputs_name_the_key():
    with pytest.raises(ConfigError) as err:
        max_distance_m(1.2, Photodiode())
    assert err.value.key == "reflectance"
    with pytest.raises(ConfigError) as err:
        max_distance_m(0.5, Photodiode(), beta_per_m=-1.0)
    assert err.value.key == "beta_per_m"


@settings(max_examples=40, deadline=None)
@given(
    refl=st.floats(0.0, 1.0),
    beta=st.one_of(st.just(0.0), st.floats(0.0, 1e4)),
    klux=st.floats(0.0, 100.0),
    noise=st.floats(0.0, 1e6),
)
def test_range_is_finite_and_bounded_for_extremes(refl, beta, klux, noise):
    from nirspi_pipe.physics.light import Background

    det = replace(Photodiode(), read_noise_e=noise)
    z = max_distance_m(
        refl,
        det,
        beta_per_m=beta,
        photon_irradiance=Background(klux=klux).photon_irradiance,
        backscatter_gain=0.01,
        fog_extent_m=0.35,
    )
    assert np.isfinite(z) and 1e-3 <= z <= 10.0
    if refl == 0.0:
        assert z == 1e-3


@settings(max_examples=25, deadline=None)
@given(
    refl=st.floats(0.0, 1.0),
    beta=st.floats(0.0, 50.0),
    gain=st.floats(0.0, 2.0),
)
def test_remembered_range_is_the_computed_one(refl, beta, gain):
    """max_distance_m remembers its result for hashable arguments (the jobs of a sweep repeat
    them): the remembered value is the computed one to the bit, and an array condition (not
    hashable) is computed each time."""
    det = Photodiode()
    cond = {"beta_per_m": beta, "backscatter_gain": gain}
    fresh = rm._max_distance(refl, det, 1.0, 1e-3, 10.0, cond)
    before = rm._remembered_max_distance.cache_info().hits
    assert max_distance_m(refl, det, **cond) == fresh
    assert max_distance_m(refl, det, **cond) == fresh
    assert rm._remembered_max_distance.cache_info().hits >= before + 1
    arr = {"beta_per_m": beta, "backscatter_gain": np.array(gain)}
    assert max_distance_m(refl, det, **arr) == rm._max_distance(refl, det, 1.0, 1e-3, 10.0, arr)
