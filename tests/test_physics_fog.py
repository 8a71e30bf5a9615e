"""Fog physics: Eq. (5), Mie efficiencies, Eq. (6), Beer–Lambert, Koschmieder (Eqs. 7–9), Eq. (12)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics import fog as F


def test_eq5_droplet_diameter_at_1_7_mhz():
    d = F.droplet_diameter_m(1.7e6)
    assert d == pytest.approx(2.9e-6, abs=0.05e-6)


def test_eq5_scales_as_f_to_minus_two_thirds():
    assert F.droplet_diameter_m(108.3e3) / F.droplet_diameter_m(1.7e6) == pytest.approx((1.7e6 / 108.3e3) ** (2 / 3))


def test_mie_qext_of_3um_water_droplet_at_1550nm_is_about_3_8_not_0_8():
    q = F.mie_efficiencies(3e-6, 1550e-9)
    assert 3.7 < q.q_ext < 3.95
    assert q.q_sca < q.q_ext  # water absorbs a little at 1550 nm
    assert q.q_ext - q.q_sca < 0.01 * q.q_ext


def test_mie_limits_small_and_large_spheres():
    assert F.mie_efficiencies(0.05e-6, 1550e-9).q_ext < 1e-3  # Rayleigh regime
    assert F.mie_efficiencies(300e-6, 1550e-9).q_ext == pytest.approx(2.0, abs=0.05)  # extinction paradox


def test_eq6_beta_is_density_times_cross_section():
    beta = F.extinction_per_m(1e10, 3e-6, 3.84)
    assert beta == pytest.approx(1e10 * np.pi * (1.5e-6) ** 2 * 3.84)


def test_beer_lambert_and_koschmieder():
    assert F.transmittance(0.0, np.inf) == 1.0
    assert F.transmittance(2.0, np.inf) == 0.0
    assert F.transmittance(2.0, 0.5) == pytest.approx(np.exp(-1.0))
    assert F.koschmieder_radiance(0.8, 0.3, 1.0, 0.0) == pytest.approx(0.8)
    assert F.koschmieder_radiance(0.8, 0.3, 1.0, 1e9) == pytest.approx(0.3)
    assert F.koschmieder_contrast(1.0, 2.0, F.visibility_m(2.0)) == pytest.approx(0.05)
    assert F.visibility_m(1.0) == pytest.approx(-np.log(0.05))
    assert F.visibility_m(0.0) == np.inf


def test_backscatter_rises_from_zero_to_its_gain():
    z = np.linspace(0.0, 100.0, 50)
    b = F.backscatter(0.1, 2.0, 1.0, z)
    assert b[0] == 0.0 and b[-1] == pytest.approx(0.2)
    assert np.all(np.diff(b) >= 0)


def test_mie_fog_uses_eq5_or_the_given_diameter():
    assert F.MieFog().diameter_m == pytest.approx(F.droplet_diameter_m(1.7e6))
    assert F.MieFog(droplet_diameter_um=5.0).diameter_m == pytest.approx(5e-6)
    fog = F.MieFog()
    r = fog.diameter_m / 2
    assert fog.extinction_per_m == pytest.approx(fog.number_density_per_cm3 * 1e6 * np.pi * r * r * fog.mie.q_ext)
    d = fog.derived()
    for key in ("droplet_diameter_um", "beta_per_m", "visibility_m", "q_ext"):
        assert np.isfinite(d[key])


def test_mie_is_lazy(monkeypatch):
    import miepython

    def boom(*a, **k):
        raise AssertionError("Mie called")

    monkeypatch.setattr(miepython, "efficiencies", boom)
    fog = F.MieFog(number_density_per_cm3=1e4)  # building the model does not call Mie
    with pytest.raises(AssertionError, match="Mie called"):
        _ = fog.extinction_per_m


@pytest.mark.parametrize(
    ("cls", "kwargs", "key"),
    [
        (F.MieFog, {"number_density_per_cm3": -1.0}, "number_density_per_cm3"),
        (F.MieFog, {"piezo_frequency_hz": 0.0}, "piezo_frequency_hz"),
        (F.MieFog, {"droplet_diameter_um": -3.0}, "droplet_diameter_um"),
        (F.MieFog, {"extent_mm": 0.0}, "extent_mm"),
        (F.MieFog, {"fluctuation_rel": 2.0}, "fluctuation_rel"),
        (F.MeasuredFog, {"beta_per_m": -0.1}, "beta_per_m"),
        (F.MeasuredFog, {"beta_per_m": float("nan")}, "beta_per_m"),
        (F.MeasuredFog, {"backscatter_gain": -1.0}, "backscatter_gain"),
    ],
)
def test_impossible_fog_inputs_name_the_key(cls, kwargs, key):
    with pytest.raises(ConfigError) as err:
        cls(**kwargs)
    assert err.value.key == key


@settings(max_examples=40, deadline=None)
@given(beta=st.floats(0.0, 1e6), z=st.floats(0.0, 1e4), l0=st.floats(0.0, 1.0), lf=st.floats(0.0, 1.0))
def test_koschmieder_stays_finite_and_between_object_and_fog(beta, z, l0, lf):
    t = F.transmittance(beta, z)
    assert 0.0 <= t <= 1.0
    l = F.koschmieder_radiance(l0, lf, beta, z)
    assert np.isfinite(l) and min(l0, lf) - 1e-12 <= l <= max(l0, lf) + 1e-12
