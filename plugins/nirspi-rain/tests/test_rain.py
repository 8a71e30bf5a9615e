"""The rain effect on its own, and inside nirspi-pipe's chain through the installed plugin."""

from __future__ import annotations

import math

import numpy as np
import pytest
from nirspi_rain import Rain, rain_extinction_per_m

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.metrics import ImageMetrics
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.physics.fog import MeasuredFog
from nirspi_pipe.physics.stagetypes import Exposure
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.scene.shapes import Plane
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.stages import Products
from nirspi_pipe.types import Camera

N = 8


def test_carbonneau_law_in_natural_units():
    # 25 mm/h: 1.076 * 25^0.67 = 9.38 dB/km -> 2.16e-3 /m
    assert rain_extinction_per_m(25.0) == pytest.approx(1.076 * 25**0.67 * math.log(10) / 10 / 1000)
    assert rain_extinction_per_m(0.0) == 0.0
    assert rain_extinction_per_m(50.0) > rain_extinction_per_m(10.0)


def test_rain_attenuates_the_round_trip():
    scene = Plane(distance_mm=300.0).render(Camera(N))
    idx = np.arange(N * N)
    clear = Simulator().acquire(scene, idx, N, np.random.default_rng(0))
    rain = Rain(rate_mm_per_h=400.0, extent_mm=float("inf"))
    wet = Simulator(forward_model(extra=[rain])).acquire(scene, idx, N, np.random.default_rng(0))
    # the centre pixel sees the plane at 0.3 m: e^{-2 beta 0.3} of the clear light at most
    total_clear = clear.y_pos + clear.y_neg
    total_wet = wet.y_pos + wet.y_neg
    ratio = float(total_wet[0] / total_clear[0])
    beta = rain.extinction_per_m
    assert math.exp(-2 * beta * 0.31) < ratio < math.exp(-2 * beta * 0.3) + 1e-12
    assert wet.info["effects"] == "rain" and wet.derived["rain_beta_per_m"] == beta


def test_rain_sits_after_the_fog_in_the_chain():
    model = forward_model(MeasuredFog(beta_per_m=1.0), extra=[Rain()])
    assert model.names == ("fog", "rain", "backscatter")
    assert [e.name for e in model.image] == ["fog", "rain"]  # an image effect


def test_the_reference_the_metrics_score_against_includes_the_rain():
    """Rain is a steady attenuation (``in_reference``): the normalised metrics' reference is the
    clear camera's image times the rain's round-trip transmittance, so a noise-free rainy run
    scores as perfect as a noise-free foggy one."""
    n = 16
    scene = Sphere().render(Camera(n))
    rain = Rain(rate_mm_per_h=500.0, extent_mm=float("inf"))
    assert rain.in_reference is True
    sim = Simulator(forward_model(extra=[rain]))
    acq = sim.acquire(scene, np.arange(n * n), n, np.random.default_rng(0))
    clear_ref = Simulator().reference_image(scene)
    t_rain = rain.transmittance(Exposure.static(scene, PhotonBudget()))
    assert np.ptp(t_rain[scene.mask]) > 1e-4  # the attenuation differs across the object
    assert acq.reference == pytest.approx(clear_ref * t_rain, rel=1e-12, abs=1e-15)
    # with fog too: the rain multiplies the foggy reference, and the veil is added on top
    fog = MeasuredFog(beta_per_m=2.0, backscatter_gain=0.01)
    foggy_ref = Simulator(forward_model(fog=fog)).reference_image(scene)
    wet_foggy = Simulator(forward_model(fog=fog, extra=[rain])).reference_image(scene)
    veil = foggy_ref - Simulator(forward_model(fog=MeasuredFog(beta_per_m=2.0, backscatter_gain=0.0))).reference_image(
        scene
    )
    assert wet_foggy == pytest.approx((foggy_ref - veil) * t_rain + veil, rel=1e-12, abs=1e-15)
    # the normalised metrics: perfect against the reference with the rain, not against the one without
    img = FWHTSolver().solve(acq)
    metrics = ImageMetrics()
    assert metrics.compute(Products(scene, acq, img))["psnr"] >= 100.0
    assert metrics.score(scene.radiance, img.data, clear_ref)["psnr"] < 100.0


def test_bad_rate_names_its_key():
    with pytest.raises(ConfigError, match="rate_mm_per_h"):
        Rain(rate_mm_per_h=-1.0)


def test_the_installed_plugin_adds_the_effect_through_the_config():
    """Through the entry point: nirspi-pipe composes source=simulator_rain and runs it."""
    from hydra import compose, initialize_config_module

    from nirspi_pipe.app.plugins import activate, discover
    from nirspi_pipe.pipeline import run_pipeline

    report = discover(refresh=True)
    assert "rain" in {p.name for p in report.plugins}, report
    activate()
    # the effect chain of this test is pinned, whatever the default run enables (no light, ideal detector)
    overrides = ["camera.resolution=8", "fog=measured", "illumination=none", "detector=ideal", "output.images=false"]
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        wet_cfg = compose(
            "config", overrides=["source=simulator_rain", "source.effects.extra.0.rate_mm_per_h=100", *overrides]
        )
        dry_cfg = compose("config", overrides=overrides)
    wet, dry = run_pipeline(wet_cfg), run_pipeline(dry_cfg)
    assert wet.products.acquisition.info["effects"] == "fog,rain,backscatter"
    assert wet.derived["rain_rate_mm_per_h"] == 100.0
    assert wet.derived["signal_photons_per_pattern"] < dry.derived["signal_photons_per_pattern"]
    # the reference the run's metrics scored against has the rain in it
    wet_ref, dry_ref = wet.products.acquisition.reference, dry.products.acquisition.reference
    assert (wet_ref < dry_ref)[wet.products.acquisition.truth.mask].all()
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        bad = compose(
            "config", overrides=["source=simulator_rain", "source.effects.extra.0.rate_mm_per_h=-5", *overrides]
        )
    with pytest.raises(ConfigError, match=r"rate_mm_per_h=-5"):
        run_pipeline(bad)
