"""The device preset (preset=device, issue 11): the paper's 8 x 8 LED camera with FSRCNN x4, and
the 64² study reachable from the same experiments with '~preset' camera.resolution=64."""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from nirspi_pipe.metrics import PSNR_CAP_DB
from nirspi_pipe.pipeline import run_pipeline

CONFIG_MODULE = "nirspi_pipe.conf"


def _compose(overrides: list[str]):
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return compose("config", overrides=overrides)


def test_device_preset_is_the_papers_camera() -> None:
    cfg = _compose(["preset=device"])
    assert cfg.camera.resolution == 8  # §3: an array of 8 x 8 NIR LEDs
    assert cfg.camera.fov_deg == pytest.approx(20.0)  # Table 1: alpha_FOV = 10° half angle
    assert cfg.upscale.scale == 4 and "fsrcnn" in cfg.upscale._target_.lower()
    assert "Photodiode" in cfg.source.effects.detector._target_


def test_the_64_study_composes_from_a_device_experiment() -> None:
    cfg = _compose(["+experiment=table3", "~preset", "camera.resolution=64"])
    assert cfg.camera.resolution == 64
    assert cfg.get("upscale") is None
    assert cfg.illumination.spectrum == "sun" and cfg.fog.fluctuation_rel == pytest.approx(0.2)


@pytest.mark.parametrize("klux", [5.0, 50.0])
def test_noise_free_device_run_is_exact_at_8_and_resolution_limited_at_32(klux: float) -> None:
    """Noise-free device in the fog chamber under daylight: the camera's 8² image scores at the
    PSNR cap (an exact reconstruction after the gain/offset normalisation), and the x4 upscaled
    image is limited by resolution alone: finite, and far below the cap (docs/paper.md, Figure 9)."""
    cfg = _compose(
        [
            "preset=device",
            "detector=ideal",
            "fog=chamber",
            "illumination=klux",
            f"illumination.klux={klux}",
            "metrics=upscale",
            "scene=sphere",
            "seed=0",
        ]
    )
    out = run_pipeline(cfg)
    assert out.metrics["psnr"] >= 100.0
    assert out.metrics["psnr"] == pytest.approx(PSNR_CAP_DB)
    up = out.metrics["upscale_psnr"]
    assert np.isfinite(up) and 10.0 < up < 60.0
    assert out.products.upscaled.data.shape == (32, 32)


@pytest.mark.parametrize(
    ("mechanism", "detector", "fog", "light"),
    [
        ("none", "Ideal", False, False),
        ("additive", "Photodiode", False, False),
        ("fog_trend", "Ideal", True, False),
        ("led_droop", "Ideal", False, False),
        ("flicker", "Ideal", False, True),
    ],
)
def test_scan_order_mechanisms_switch_on_one_effect_each(mechanism: str, detector: str, fog: bool, light: bool) -> None:
    """experiments/mechanism/*.yaml: each mechanism of the scan-order study on the device model, alone."""
    cfg = _compose(["+experiment=scan_order", f"mechanism={mechanism}"])
    assert cfg.camera.resolution == 8 and cfg.upscale.scale == 4
    assert detector in cfg.source.effects.detector._target_
    assert ("NoFog" not in cfg.fog._target_) is fog
    assert ((cfg.illumination or {}).get("klux", 0.0) > 0) is light
    if fog:
        assert cfg.fog.trend_rel == pytest.approx(0.3)
    if light:
        assert cfg.illumination.flicker_rel == pytest.approx(0.05)
    droop = cfg.source.effects.get("led_droop_rel", 0.0) or 0.0
    assert (droop != 0.0) is (mechanism == "led_droop")
