"""The simulator: composed of the configured effects only, exact ideal path, derived
quantities, time-varying effects and scan order, hard cases."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import ifwht2, pattern
from nirspi_pipe.physics.detector import IdealDetector, Photodiode
from nirspi_pipe.physics.effects import ForwardModel, forward_model
from nirspi_pipe.physics.fog import MeasuredFog, NoFog
from nirspi_pipe.physics.light import Background
from nirspi_pipe.physics.splitmeasure import modulated_split
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.scene.shapes import Plane
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera

ISSUE_KEYS = (
    "beta_per_m",
    "transmittance_roundtrip",
    "signal_photons_per_pattern",
    "background_photons_per_pattern",
    "background_irradiance_w_m2",
    "snr_db",
    "saturated_patterns",
)
FOG_KEYS = ("droplet_diameter_um", "visibility_m")


def _compose(overrides):
    from hydra import compose, initialize_config_module

    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        return compose("config", overrides=overrides)


def _run(overrides):
    from nirspi_pipe.pipeline import run_pipeline

    return run_pipeline(_compose(overrides))


def _reconstruct(acq):
    n = acq.n
    c = np.zeros(n * n)
    c[acq.indices] = acq.coefficients()
    return ifwht2(c.reshape(n, n))


@pytest.fixture(scope="module")
def sphere16():
    return Sphere().render(Camera(16))


@pytest.mark.parametrize("scene", ["sphere", "image", "torus", "cube", "u_shape", "plane"])
def test_ideal_path_reconstructs_radiance_exactly(scene):
    out = _run([f"scene={scene}", "camera.resolution=32", "fog=none", "illumination=none", "detector=ideal"])
    assert np.abs(out.products.image.data - out.products.truth.radiance).max() < 1e-9
    assert out.products.acquisition.gain == 1.0
    assert out.products.acquisition.info["effects"] == ""


def test_fog_none_never_calls_mie(monkeypatch):
    import miepython

    import nirspi_pipe.physics.fog as fogmod

    def boom(*a, **k):
        raise AssertionError("Mie was called")

    monkeypatch.setattr(miepython, "efficiencies", boom)
    monkeypatch.setattr(fogmod, "mie_efficiencies", boom)
    out = _run(["fog=none", "illumination=klux", "detector=ingaas", "camera.resolution=16"])
    assert "fog" not in out.products.acquisition.info["effects"]
    assert out.derived["beta_per_m"] == 0.0 and out.derived["transmittance_roundtrip"] == 1.0
    assert not any(k in out.derived for k in FOG_KEYS)
    with pytest.raises(AssertionError, match="Mie was called"):
        _run(["fog=chamber", "camera.resolution=16"])


def test_inactive_effects_are_not_built():
    sim = Simulator(forward_model(fog=NoFog(), illumination=Background(klux=0.0), detector=IdealDetector()))
    assert sim.effects == ForwardModel() and sim.effect_names == ()


def test_derived_quantities_of_a_full_run():
    out = _run(["fog=chamber", "illumination=klux", "illumination.klux=15", "detector=ingaas", "camera.resolution=16"])
    d = out.derived
    for key in ISSUE_KEYS + FOG_KEYS + ("range_max_m",):
        assert key in d and np.isfinite(d[key]), key
    assert d["droplet_diameter_um"] == pytest.approx(2.9, abs=0.05)
    assert d["transmittance_roundtrip"] == pytest.approx(np.exp(-2 * d["beta_per_m"] * 0.2))
    assert d["visibility_m"] == pytest.approx(-np.log(0.05) / d["beta_per_m"])
    assert d["background_irradiance_w_m2"] > 0 and d["background_photons_per_pattern"] > 0
    eff = out.products.acquisition.info["effects"].split(",")
    assert eff == ["budget", "fog", "backscatter", "background", "detector"]


def test_physical_reconstruction_is_calibrated_relative_radiance():
    scene = Plane(reflectance=0.5).render(Camera(16))
    acq = Simulator(forward_model(detector=Photodiode(shot_noise=False, read_noise_e=0.0, adc_bits=None))).acquire(
        scene, np.arange(256), 16, np.random.default_rng(0)
    )
    img = _reconstruct(acq)
    # a flat board: relative radiance with the 1/r² fall-off towards the corners (cos θ of the rays)
    assert img[7:9, 7:9].mean() == pytest.approx(scene.radiance[7:9, 7:9].mean(), rel=2e-3)
    assert img[0, 0] < img[8, 8]


def test_fog_attenuates_by_the_round_trip_transmittance():
    scene = Plane(reflectance=0.5).render(Camera(8))
    idx = np.arange(64)
    clear = Simulator().acquire(scene, idx, 8, np.random.default_rng(0))
    fog = MeasuredFog(beta_per_m=3.0, backscatter_gain=0.0)
    foggy = Simulator(forward_model(fog=fog)).acquire(scene, idx, 8, np.random.default_rng(0))
    ratio = foggy.coefficients()[0] / clear.coefficients()[0]
    u, v = scene.camera.pixel_coords(1)
    r = scene.depth_m * np.sqrt(1 + u[..., 0] ** 2 + v[..., 0] ** 2)  # range along each pixel's ray
    want = np.sum(scene.radiance * np.exp(-2 * 3.0 * r)) / np.sum(scene.radiance)
    assert ratio == pytest.approx(want, rel=1e-9)
    assert 0.95 < ratio / np.exp(-2 * 3.0 * 0.2) <= 1.0


@pytest.mark.parametrize("extent_mm", [1e-9, 100.0, 200.0, 350.0, float("inf")])
def test_derived_transmittance_follows_the_fog_path(extent_mm):
    """derived.transmittance_roundtrip is Eq. (7) over the fog's path to the nominal distance,
    min(distance, extent): a chamber shorter than the distance attenuates less (issue 40: it used
    the distance alone, so a 1e-9 mm fog path reported 63 % of the light surviving)."""
    scene = Plane(reflectance=0.5).render(Camera(8))  # 200 mm away
    fog = MeasuredFog(beta_per_m=3.0, backscatter_gain=0.0, extent_mm=extent_mm)
    acq = Simulator(forward_model(fog=fog)).acquire(scene, np.arange(64), 8, np.random.default_rng(0))
    path_m = min(0.2, extent_mm * 1e-3)
    assert acq.derived["transmittance_roundtrip"] == pytest.approx(np.exp(-2 * 3.0 * path_m), rel=1e-12)
    clear = Simulator().acquire(scene, np.arange(64), 8, np.random.default_rng(0))
    assert clear.derived["transmittance_roundtrip"] == 1.0


def test_static_background_cancels_and_drift_makes_the_order_matter(sphere16):
    n = 16
    order = np.arange(n * n)
    static = Simulator(forward_model(illumination=Background(klux=50.0)))
    for idx in (order, order[::-1]):
        acq = static.acquire(sphere16, idx, n, np.random.default_rng(0))
        assert np.abs(_reconstruct(acq) - sphere16.radiance).max() < 1e-9
    # a linear drift offsets every pair equally (only the DC pixel moves, whatever the order);
    # flicker and slow wander differ from pair to pair, so the order decides where errors land
    drift = Simulator(
        forward_model(
            illumination=Background(klux=50.0, drift_rel_per_s=0.2, flicker_rel=0.02, flicker_hz=7.0, wander_rel=0.01)
        )
    )
    a = _reconstruct(drift.acquire(sphere16, order, n, np.random.default_rng(0)))
    b = _reconstruct(drift.acquire(sphere16, order[::-1], n, np.random.default_rng(0)))
    err_a, err_b = np.abs(a - sphere16.radiance).max(), np.abs(b - sphere16.radiance).max()
    assert err_a > 1e-3 and err_b > 1e-3
    assert np.abs(a - b).max() > 1e-3


def test_fog_fluctuation_makes_the_order_matter(sphere16):
    n = 16
    order = np.arange(n * n)
    sim = Simulator(forward_model(fog=MeasuredFog(beta_per_m=3.0, fluctuation_rel=0.2, fluctuation_time_s=0.02)))
    a = _reconstruct(sim.acquire(sphere16, order, n, np.random.default_rng(0)))
    b = _reconstruct(sim.acquire(sphere16, order[::-1], n, np.random.default_rng(0)))
    assert np.abs(a - b).max() > 1e-3
    again = _reconstruct(sim.acquire(sphere16, order, n, np.random.default_rng(0)))
    assert np.array_equal(a, again)  # seeded


@pytest.mark.parametrize("scale", [1.0, 40.0])  # Taylor series, then the interpolated levels
def test_modulated_split_matches_brute_force(scale):
    n = 8
    rng = np.random.default_rng(0)
    base = rng.random((n, n))
    x = scale * rng.random((n, n))
    idx = rng.permutation(n * n)[:20]
    c_pos = 1.0 + 0.3 * rng.standard_normal(20)
    c_neg = 1.0 + 0.3 * rng.standard_normal(20)
    pos, neg = modulated_split(base, x, c_pos, c_neg, idx)
    for k, i in enumerate(idx):
        p = pattern(int(i), n)
        want_pos = np.sum(0.5 * (1 + p) * base * np.exp(-c_pos[k] * x))
        want_neg = np.sum(0.5 * (1 - p) * base * np.exp(-c_neg[k] * x))
        tol = 1e-9 if scale == 1.0 else 2e-2
        assert pos[k] == pytest.approx(want_pos, rel=tol, abs=tol * base.sum())
        assert neg[k] == pytest.approx(want_neg, rel=tol, abs=tol * base.sum())


def test_saturation_is_counted_and_warned():
    scene = Plane(distance_mm=30.0, reflectance=1.0).render(Camera(8))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        acq = Simulator(forward_model(detector=Photodiode())).acquire(scene, np.arange(64), 8, np.random.default_rng(0))
    assert acq.derived["saturated_patterns"] > 0
    assert any("saturated" in str(w.message) for w in caught)
    assert np.isfinite(acq.coefficients()).all()


def test_impossible_inputs_name_the_key():
    from nirspi_pipe.pipeline import run_pipeline

    for overrides, key in (
        (["fog=chamber", "fog.number_density_per_cm3=-5"], "fog.number_density_per_cm3"),
        (["scene.reflectance=1.5"], "scene.reflectance"),
        (["illumination=klux", "illumination.klux=-1"], "illumination.klux"),
        (["detector=ingaas", "detector.budget.t_int_us=0"], "detector.budget.t_int_us"),
        (["fog=measured", "fog.beta_per_m=-1"], "fog.beta_per_m"),
    ):
        with pytest.raises(ConfigError) as err:
            run_pipeline(_compose(overrides))
        assert err.value.key == key, overrides


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    beta=st.one_of(st.just(0.0), st.floats(0.0, 1e3)),
    distance_mm=st.floats(1.0, 10000.0),
    klux=st.floats(0.0, 100.0),
    refl=st.floats(0.0, 1.0),
    fluct=st.sampled_from([0.0, 0.3]),
    drift=st.sampled_from([0.0, 1.0]),
    physical=st.booleans(),
)
def test_hard_cases_stay_finite_and_in_range(beta, distance_mm, klux, refl, fluct, drift, physical):
    n = 4
    scene = Plane(distance_mm=distance_mm, reflectance=refl).render(Camera(n))
    det = Photodiode() if physical else IdealDetector()
    sim = Simulator(
        forward_model(
            fog=MeasuredFog(beta_per_m=beta, fluctuation_rel=fluct) if beta > 0 else None,
            illumination=Background(klux=klux, drift_rel_per_s=drift),
            detector=det,
        )
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        acq = sim.acquire(scene, np.arange(n * n), n, np.random.default_rng(0))
    for arr in (acq.y_pos, acq.y_neg, acq.coefficients(), _reconstruct(acq)):
        assert np.isfinite(arr).all()
    for key, value in acq.derived.items():
        assert np.isfinite(value), key
    if physical:
        top = 2**16 - 1
        assert (acq.y_pos >= 0).all() and (acq.y_pos <= top).all() and (acq.y_neg <= top).all()
    else:
        assert (acq.y_pos >= -1e-9).all()
    assert 0 <= acq.derived["saturated_patterns"] <= 2 * n * n + sim.dark_readings


def test_zero_signal_is_finite():
    scene = Plane(reflectance=0.0).render(Camera(8))
    for det in (IdealDetector(), Photodiode()):
        acq = Simulator(forward_model(detector=det)).acquire(scene, np.arange(64), 8, np.random.default_rng(0))
        assert acq.derived["signal_photons_per_pattern"] == 0.0
        assert acq.derived["snr_db"] == -200.0
        assert np.isfinite(_reconstruct(acq)).all()
        assert all(np.isfinite(v) for v in acq.derived.values())


def test_full_saturation_is_counted():
    scene = Plane(distance_mm=1.0, reflectance=1.0).render(Camera(8))
    sim = Simulator(forward_model(illumination=Background(klux=100.0), detector=Photodiode()))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        acq = sim.acquire(scene, np.arange(64), 8, np.random.default_rng(0))
    assert acq.derived["saturated_patterns"] == 2 * 64 + sim.dark_readings
    assert acq.derived["saturated_fraction"] == 1.0
    assert np.all(acq.y_pos == 2**16 - 1) and np.allclose(acq.coefficients(), 0.0)


def test_enabling_one_effect_does_not_change_another_effects_noise(sphere16):
    idx = np.arange(256)
    a = Simulator(forward_model(detector=Photodiode())).acquire(sphere16, idx, 16, np.random.default_rng(5))
    b = Simulator(forward_model(detector=Photodiode(), illumination=Background(klux=1e-9))).acquire(
        sphere16, idx, 16, np.random.default_rng(5)
    )
    assert np.array_equal(a.y_pos, b.y_pos)  # the detector's stream is its own
