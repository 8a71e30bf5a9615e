"""Each effect of the forward-model chain on its own (nirspi_pipe.physics.effects)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.detector import IdealDetector, Photodiode
from nirspi_pipe.physics.effects import (
    Backscatter,
    DetectorReadout,
    FogAttenuation,
    FogFluctuation,
    ForwardModel,
    GaussianNoise,
    LedDroop,
    forward_model,
)
from nirspi_pipe.physics.fog import MeasuredFog, NoFog
from nirspi_pipe.physics.light import Background
from nirspi_pipe.physics.lighteffects import BackgroundDrift, BackgroundLight, Illumination
from nirspi_pipe.physics.stagetypes import Effect, Exposure, ImageState, Readings, ideal_readout, measure
from nirspi_pipe.scene.shapes import Plane
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera

N = 8


def _exposure(distance_mm: float = 200.0, reflectance: float = 0.5, n_dark: int = 0, streams: int = 3) -> Exposure:
    scene = Plane(distance_mm=distance_mm, reflectance=reflectance).render(Camera(N))
    m = N * N
    t_pos = (n_dark + 2.0 * np.arange(m)) * 1e-3
    rng = np.random.default_rng(3)
    return Exposure(
        scene=scene,
        indices=np.arange(m),
        n=N,
        t_pos=t_pos,
        t_neg=t_pos + 1e-3,
        t_dark=np.arange(n_dark) * 1e-3,
        budget=PhotonBudget(),
        rngs=tuple(rng.spawn(streams)),
        rng_main=rng,
    )


def _start(ex: Exposure) -> ImageState:
    return ImageState(image_e=ex.scene.radiance * ex.ref_e)


def _readings(ex: Exposure, image: ImageState | None = None) -> Readings:
    return measure(_start(ex) if image is None else image, ex)


def test_illumination_falls_off_as_inverse_square():
    near, far = _exposure(200.0), _exposure(400.0)
    a = Illumination().apply(_start(near), near).image_e
    b = Illumination().apply(_start(far), far).image_e
    # the same pixels see the plane at twice the range: a quarter of the light (Eqs. 10-11)
    centre = (N // 2, N // 2)
    assert b[centre] / a[centre] == pytest.approx(0.25, rel=1e-9)
    assert (a >= 0).all()


@settings(max_examples=20, deadline=None)
@given(beta=st.floats(0.0, 50.0))
def test_fog_attenuation_is_beer_lambert_on_the_round_trip(beta):
    ex = _exposure()
    s = measure(FogAttenuation(MeasuredFog(beta_per_m=beta)).apply(_start(ex), ex), ex)
    expected = float((ex.scene.radiance * ex.ref_e * np.exp(-2.0 * beta * ex.range_m)).sum())
    assert s.pos_e + s.neg_e == pytest.approx(np.full(N * N, expected), rel=1e-9, abs=1e-300)
    assert s.beta_per_m == beta and s.conditions["fog_extent_m"] == pytest.approx(0.35)


def test_fog_fluctuation_needs_fog_first_and_is_seeded():
    ex = _exposure()
    with pytest.raises(ValueError, match="follow the fog"):
        FogFluctuation(0.2).apply(_start(ex), ex)
    fogged = FogAttenuation(MeasuredFog(beta_per_m=3.0)).apply(_start(ex), ex)
    a = FogFluctuation(0.2, 0.01).apply(fogged, ex)
    b = FogFluctuation(0.2, 0.01).apply(fogged, _exposure())
    assert a.medium is not None and a.medium.fluctuation is not None
    assert b.medium is not None and b.medium.fluctuation is not None
    assert np.array_equal(a.medium.fluctuation[0], b.medium.fluctuation[0])
    assert (a.medium.fluctuation[0] >= 0).all() and a.derived["fog_factor_std"] > 0
    with pytest.raises(ConfigError, match="fluctuation_rel"):
        FogFluctuation(2.0)


def test_backscatter_adds_the_eq12_veil_to_every_reading():
    ex = _exposure(distance_mm=1000.0)
    fogged = FogAttenuation(MeasuredFog(beta_per_m=2.0, backscatter_gain=0.0)).apply(_start(ex), ex)
    clear = measure(fogged, ex)
    veiled = Backscatter(0.05).apply(clear, ex)
    white_1m = float(ex.budget.white_electrons(1.0)) / (N * N)
    veil = 0.05 * white_1m * (1.0 - np.exp(-2.0 * np.minimum(ex.range_m, 0.35)))
    added = (veiled.pos_e + veiled.neg_e) - (clear.pos_e + clear.neg_e)
    assert added == pytest.approx(np.full(N * N, veil.sum()), rel=1e-9)
    with pytest.raises(ValueError, match="follow the fog"):
        Backscatter(0.05).apply(_readings(ex), ex)


def test_background_light_cancels_in_the_difference():
    ex = _exposure()
    base = _readings(ex)
    lit = BackgroundLight(Background(klux=30.0)).apply(base, ex)
    pos, neg = lit.total_e()
    assert lit.background_e > 0
    assert pos - neg == pytest.approx(base.pos_e - base.neg_e, abs=1e-6 * lit.background_e)
    assert pos.mean() > base.pos_e.mean()


def test_background_drift_no_longer_cancels():
    ex = _exposure()
    with pytest.raises(ValueError, match="follow the background"):
        BackgroundDrift(drift_rel_per_s=1.0).apply(_readings(ex), ex)
    lit = BackgroundLight(Background(klux=30.0)).apply(_readings(ex), ex)
    drift = BackgroundDrift(drift_rel_per_s=5.0).apply(lit, ex)
    assert drift.ambient is not None
    assert np.all(np.asarray(drift.ambient.neg) > np.asarray(drift.ambient.pos))  # later readings see more light
    assert drift.derived["background_factor_std"] > 0


def test_detector_readout_is_charge_plus_pedestal_in_counts():
    ex = _exposure(n_dark=4)
    det = Photodiode(shot_noise=False, read_noise_e=0.0, dark_current_na=0.0, adc_bits=None, full_scale_v=None)
    r = _readings(ex, Illumination().apply(_start(ex), ex))
    s = DetectorReadout(det).read(r, ex)
    pos_e, _ = r.total_e()
    assert s.y_pos == pytest.approx(pos_e + det.offset_e, rel=1e-12)
    assert s.saturated == 0 and s.gain == pytest.approx(ex.ref_e)


def test_detector_counts_and_warns_saturation():
    ex = _exposure(distance_mm=10.0, reflectance=1.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = DetectorReadout(Photodiode()).read(_readings(ex, Illumination().apply(_start(ex), ex)), ex)
    assert s.saturated > 0
    assert any("saturated" in str(w.message) for w in caught)


def test_detector_without_saturation_does_not_warn():
    ex = _exposure()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = DetectorReadout(Photodiode()).read(_readings(ex, Illumination().apply(_start(ex), ex)), ex)
    assert s.saturated == 0 and not caught


def test_gaussian_noise_has_the_stated_sigma():
    ex = _exposure()
    clean = ideal_readout(_readings(ex), ex)
    noisy = GaussianNoise(0.01).apply(clean, ex)
    sigma = 0.01 * 0.5 * float(ex.scene.radiance.sum())
    assert noisy.derived["noise_sigma"] == pytest.approx(sigma)
    resid = np.concatenate([noisy.y_pos - clean.y_pos, noisy.y_neg - clean.y_neg])
    assert np.std(resid) == pytest.approx(sigma, rel=0.15)  # 128 draws
    with pytest.raises(ConfigError, match="noise_rel"):
        GaussianNoise(-1.0)


def test_forward_model_leaves_out_what_is_off_and_keeps_the_order():
    assert forward_model(NoFog(), Background(klux=0.0), IdealDetector(), 0.0) == ForwardModel()
    model = forward_model(
        MeasuredFog(beta_per_m=1.0, fluctuation_rel=0.1), Background(klux=5.0, flicker_rel=0.1), Photodiode(), 0.01
    )
    assert list(model.names) == [
        "budget",
        "fog",
        "fog_fluctuation",
        "backscatter",
        "background",
        "background_drift",
        "detector",
        "gaussian_noise",
    ]
    assert all(isinstance(e, Effect) for e in model.effects)
    assert [e.name for e in model.image] == ["budget", "fog", "fog_fluctuation"]
    assert [e.name for e in model.readings] == ["backscatter", "background", "background_drift"]
    assert isinstance(model.readout, DetectorReadout) and [e.name for e in model.output] == ["gaussian_noise"]
    with pytest.raises(ConfigError, match="detector"):
        forward_model(detector="ingaas")


@dataclass(frozen=True)
class _Haze:
    """A plugin-style effect: a grey filter in the image stage."""

    transmission: float
    in_reference: bool = True
    name: ClassVar[str] = "haze"
    domain: ClassVar[Literal["image"]] = "image"

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        return replace(image, image_e=image.image_e * self.transmission)


@dataclass(frozen=True)
class _Offset:
    """A plugin-style reading effect: a constant extra charge on every reading (not in the reference)."""

    charge_e: float
    name: ClassVar[str] = "offset"
    domain: ClassVar[Literal["readings"]] = "readings"
    in_reference: ClassVar[bool] = False

    def apply(self, readings: Readings, exposure: Exposure) -> Readings:
        return replace(readings, pos_e=readings.pos_e + self.charge_e, neg_e=readings.neg_e + self.charge_e)


def test_a_new_effect_is_one_small_class():
    scene = Plane().render(Camera(N))
    idx = np.arange(N * N)
    model = forward_model(MeasuredFog(beta_per_m=1.0), extra=[_Haze(0.5)])
    assert model.names == ("fog", "haze", "backscatter")
    plain = Simulator(ForwardModel(image=model.image[:1]))
    hazy = Simulator(ForwardModel(image=model.image[:2]))
    a = plain.acquire(scene, idx, N, np.random.default_rng(0))
    b = hazy.acquire(scene, idx, N, np.random.default_rng(0))
    assert b.y_pos == pytest.approx(0.5 * a.y_pos) and b.info["effects"] == "fog,haze"


def test_the_reference_is_exactly_the_effects_in_it():
    """``in_reference`` decides: the haze in it halves the reference, out of it leaves it alone."""
    scene = Plane().render(Camera(N))
    clear = Simulator().reference_image(scene)
    assert Simulator(forward_model(extra=[_Haze(0.5)])).reference_image(scene) == pytest.approx(0.5 * clear)
    assert np.array_equal(
        Simulator(forward_model(extra=[_Haze(0.5, in_reference=False)])).reference_image(scene), clear
    )
    assert np.array_equal(Simulator(forward_model(extra=[_Offset(10.0)])).reference_image(scene), clear)


def test_the_built_in_effects_declare_their_stage_and_reference():
    model = forward_model(
        MeasuredFog(beta_per_m=1.0, fluctuation_rel=0.1, trend_rel=0.1),
        Background(klux=5.0, flicker_rel=0.1),
        Photodiode(),
        0.01,
        led_droop_rel=-0.01,
    )
    in_ref = {e.name: e.in_reference for e in (*model.image, *model.readings)}
    assert in_ref == {
        "budget": True,
        "fog": True,
        "fog_fluctuation": False,
        "fog_trend": False,
        "backscatter": True,
        "led_droop": False,
        "background": False,
        "background_drift": False,
    }
    assert all(e.domain == "image" for e in model.image) and all(e.domain == "readings" for e in model.readings)
    assert all(e.domain == "output" and not hasattr(e, "in_reference") for e in model.output)


@pytest.mark.parametrize(
    "effect, allowed",
    [
        (object(), "domain 'image'"),  # no stage at all
        (NoFog(), "domain 'image'"),  # a model, not an effect
        (type("_NoRef", (), {"name": "x", "domain": "image", "apply": _Haze.apply})(), "in_reference"),
        (
            type("_Where", (), {"name": "x", "domain": "optics", "in_reference": True, "apply": _Haze.apply})(),
            "'output'",
        ),
        (
            type("_RefRead", (), {"name": "x", "domain": "readings", "in_reference": True, "apply": _Offset.apply})(),
            "reference_e",
        ),
        (
            type("_RefOut", (), {"name": "x", "domain": "output", "in_reference": True, "apply": _Offset.apply})(),
            "never in it",
        ),
    ],
)
def test_an_effect_without_its_stage_is_refused_when_the_chain_is_built(effect, allowed):
    with pytest.raises(ConfigError, match="extra.1") as err:
        forward_model(extra=[_Haze(0.5), effect])
    assert allowed in str(err.value) and "\n" not in str(err.value)


def test_a_misplaced_effect_is_refused_by_its_stage():
    with pytest.raises(ConfigError, match=r"^image\.0=Backscatter"):
        ForwardModel(image=(Backscatter(0.1),))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^readings\.1=Illumination"):
        ForwardModel(readings=(LedDroop(-0.1), Illumination()))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="^output.0"):
        ForwardModel(output=(_Haze(0.5),))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="^readout"):
        ForwardModel(readout=GaussianNoise(0.1))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="^effects"):
        Simulator(effects=(Illumination(),))  # type: ignore[arg-type]


def test_a_misplaced_effect_in_a_config_is_one_line_naming_the_key():
    from nirspi_pipe.instantiate import build

    node = {
        "_target_": "nirspi_pipe.sources.simulator.Simulator",
        "effects": {
            "_target_": "nirspi_pipe.physics.effects.forward_model",
            "extra": [{"_target_": "nirspi_pipe.physics.fog.MeasuredFog", "beta_per_m": 1.0}],
        },
    }
    with pytest.raises(ConfigError) as err:
        build(node, "source")
    msg = str(err.value)
    assert msg.startswith("source.effects.extra.0=MeasuredFog(") and "\n" not in msg
    assert "domain 'image'" in msg and "'readings'" in msg and "'output'" in msg


def test_led_droop_and_fog_trend_make_the_order_matter_at_full_sampling():
    """Issue 11: a multiplicative drift in time changes the image error with the order, even with
    every pattern measured (an additive steady error would not). Without the drift the orders
    give the same image to rounding."""
    from nirspi_pipe.patterns.orders import Basic, Spiral
    from nirspi_pipe.physics.effects import FogTrend, LedDroop, forward_model
    from nirspi_pipe.physics.fog import MeasuredFog
    from nirspi_pipe.scene.objects import Sphere
    from nirspi_pipe.solvers.fwht import FWHTSolver
    from nirspi_pipe.sources.simulator import Simulator
    from nirspi_pipe.types import Camera

    n = 8
    scene = Sphere().render(Camera(n))

    def error(sim: Simulator, order: str) -> float:
        idx = {"basic": Basic(), "spiral": Spiral()}[order].select(n)
        img = FWHTSolver().solve(sim.acquire(scene, idx, n, np.random.default_rng(0))).data
        ref = sim.reference_image(scene)
        return float(np.sqrt(np.mean((img - ref) ** 2)))

    steady = Simulator(forward_model())
    assert abs(error(steady, "basic") - error(steady, "spiral")) < 1e-12
    droop = Simulator(forward_model(led_droop_rel=-0.05))
    assert droop.effect_names == ("led_droop",)
    assert abs(error(droop, "basic") - error(droop, "spiral")) > 1e-4
    trend = Simulator(forward_model(fog=MeasuredFog(beta_per_m=1.15, trend_rel=0.3, backscatter_gain=0.0)))
    assert "fog_trend" in trend.effect_names
    assert abs(error(trend, "basic") - error(trend, "spiral")) > 1e-4
    assert LedDroop(-0.05, 0.05).factor(np.array([0.0]))[0] == 1.0
    assert np.isclose(LedDroop(-0.05, 0.05).factor(np.array([1e3]))[0], 0.95)
    with pytest.raises(ConfigError):
        FogTrend(-2.0)
