"""Background light: kLux → in-band irradiance (solar-like spectrum) and the photon budget."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.light import (
    Background,
    band_fraction,
    klux_to_irradiance_w_m2,
    klux_to_photon_irradiance,
    luminous_efficacy_lm_per_w,
)


def test_solar_luminous_efficacy_and_full_sun():
    eff = luminous_efficacy_lm_per_w(5778.0)
    assert 85.0 < eff < 100.0  # sunlight: ~93 lm/W
    total = 100e3 / eff
    assert 1000.0 < total < 1200.0  # 100 kLux is about 1.1 kW/m²


def test_band_irradiance_is_linear_in_klux_and_grows_with_the_band():
    a = klux_to_irradiance_w_m2(10.0)
    assert klux_to_irradiance_w_m2(20.0) == pytest.approx(2 * a)
    assert klux_to_irradiance_w_m2(0.0) == 0.0
    assert klux_to_irradiance_w_m2(10.0, (800.0, 1700.0)) > 10 * a
    frac, photons_per_w = band_fraction((1500.0, 1600.0))
    assert 0.005 < frac < 0.05
    # photons per in-band watt ≈ λ/hc at ~1550 nm
    assert photons_per_w / frac == pytest.approx(1550e-9 / (6.626e-34 * 2.998e8), rel=0.05)
    assert klux_to_photon_irradiance(10.0) == pytest.approx(a * photons_per_w / frac, rel=1e-9)


def test_photon_budget_scaling():
    b = PhotonBudget()
    assert b.white_electrons(0.2) / b.white_electrons(0.4) == pytest.approx(4.0)
    assert PhotonBudget(led_power_mw=2.0).white_electrons(0.3) == pytest.approx(2 * b.white_electrons(0.3))
    assert PhotonBudget(f_number=2.8).white_electrons(0.3) == pytest.approx(b.white_electrons(0.3) / 4)
    assert b.white_electrons(np.inf) == 0.0
    assert b.ambient_electrons(1e18, 0.4) == pytest.approx(2 * b.ambient_electrons(1e18, 0.2))
    # Eq. (10) by hand for the defaults at 20 cm: ~1.6e5 e⁻ for a white target filling the view
    assert 1e5 < b.white_electrons(0.2) < 3e5


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"klux": -1.0}, "klux"),
        ({"klux": 150.0}, "klux"),
        ({"band_nm": (1600.0, 1500.0)}, "band_nm"),
        ({"surround_reflectance": 1.5}, "surround_reflectance"),
        ({"flicker_rel": -0.1}, "flicker_rel"),
    ],
)
def test_impossible_light_inputs_name_the_key(kwargs, key):
    with pytest.raises(ConfigError) as err:
        Background(**kwargs)
    assert err.value.key == key


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"f_number": 0.0}, "f_number"),
        ({"quantum_efficiency": 1.2}, "quantum_efficiency"),
        ({"led_count": 0}, "led_count"),
    ],
)
def test_impossible_budget_inputs_name_the_key(kwargs, key):
    with pytest.raises(ConfigError) as err:
        PhotonBudget(**kwargs)
    assert err.value.key == key


@settings(max_examples=30, deadline=None)
@given(klux=st.floats(0.0, 100.0), z=st.floats(1e-3, 10.0))
def test_budget_is_finite_over_the_range(klux, z):
    b = PhotonBudget()
    bg = Background(klux=klux)
    vals = [b.white_electrons(z), b.ambient_electrons(bg.photon_irradiance, 1.0), bg.irradiance_w_m2]
    assert all(np.isfinite(v) and v >= 0 for v in vals)


def test_sun_spectrum_is_the_astm_g173_standard():
    """AM1.5 global: ~1000 W/m² in total and 25.5 W/m² in 1500-1600 nm (ASTM G173-03); per kLux
    the band carries more than the 5778 K blackbody (issue 11: the blackbody was 23-29 % low)."""
    from nirspi_pipe.physics.light import astm_g173_global

    lam, e = astm_g173_global()
    nm = np.round(lam * 1e9, 3)
    band = (nm >= 1500) & (nm <= 1600)
    assert np.trapezoid(e[band], lam[band]) == pytest.approx(25.54, rel=1e-3)
    sun = klux_to_irradiance_w_m2(1.0, spectrum="sun")
    bb = klux_to_irradiance_w_m2(1.0, temperature_k=5778.0, spectrum="blackbody")
    assert 1.15 < sun / bb < 1.45
    assert klux_to_irradiance_w_m2(10.0, spectrum="sun") == pytest.approx(10 * sun)


def test_each_source_has_its_own_flicker():
    from nirspi_pipe.physics.light import filament_flicker_rel

    assert Background(klux=10, spectrum="sun", flicker_rel=None).flicker_rel == 0.0
    lamp = Background(klux=10, spectrum="halogen", spectrum_temperature_k=3000, flicker_rel=None, mains_hz=60)
    assert lamp.flicker_hz == 120.0 and 0 < lamp.flicker_rel < 0.25
    # more thermal inertia, less flicker; no inertia: the full quarter of the T^4 ripple times d ln B/d ln T
    taus = [1e-4, 1e-3, 1e-2, 1e-1]
    amps = [filament_flicker_rel(t) for t in taus]
    assert all(a > b for a, b in zip(amps, amps[1:], strict=False))
    assert filament_flicker_rel(0.0) > 0.25
    # a halogen lamp puts far more of its light in the InGaAs band per lux than the sun
    assert lamp.irradiance_w_m2 > 5 * Background(klux=10, spectrum="sun").irradiance_w_m2
    with pytest.raises(ConfigError):
        Background(klux=1, spectrum="moon")
