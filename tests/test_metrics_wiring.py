"""Stages wired as objects (issue 42, item 3): the metrics stages that score with the run's scene
model, source and upscaler (``metrics=upscale``, ``metrics=full``) get the stages the run built
(:class:`nirspi_pipe.stages.ScoresWithStages`), not copies of their config built a second time.

Before (at 27f888e), ``conf/metrics/{full,upscale}.yaml`` carried ``scene: ${scene}``,
``source: ${source}`` and ``upscaler: ${upscale}``: every such run built a second scene model, a
second simulator and a second FSRCNN for its metrics.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import nirspi_pipe.instantiate as instantiate
from nirspi_pipe.app.api import compose, run
from nirspi_pipe.instantiate import plain_config
from nirspi_pipe.mesh.metrics3d import Metrics3D, sample_skewness
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.stages import RunStages, ScoresWithStages
from nirspi_pipe.upscale import FSRCNN
from nirspi_pipe.upscale.metrics import UpscaleMetrics

#: The device model at its smallest: 8² camera, FSRCNN ×4 to 32² (conf/preset/device.yaml).
DEVICE = ["output.images=false", "output.arrays=false", "seed=0"]
#: The 3D stages up to the fused cloud (no surface: the power crust is the slow part).
THREE_D = ["sfs=second_order", "itof=cw4", "fusion=itof", "metrics=full"]


def _built_from_config(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """``{config path: object}`` of every ``_target_`` node the runner builds (wraps the builder's
    recursion, :func:`nirspi_pipe.instantiate._instantiate`)."""
    built: dict[str, Any] = {}
    inner = instantiate._instantiate

    def recorded(node: Any, path: str, plan: Any) -> Any:
        out = inner(node, path, plan)
        if isinstance(node, dict) and "_target_" in node:
            built[path] = out
        return out

    monkeypatch.setattr(instantiate, "_instantiate", recorded)
    return built


def _scored_with(monkeypatch: pytest.MonkeyPatch, cls: type) -> list[Any]:
    """The metrics objects whose ``compute`` ran."""
    seen: list[Any] = []
    compute = cls.compute

    def spy(self: Any, products: Any) -> Any:
        seen.append(self)
        return compute(self, products)

    monkeypatch.setattr(cls, "compute", spy)
    return seen


def _run(overrides: list[str]) -> dict[str, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return dict(run(overrides).metrics)


def test_the_upscale_metrics_score_with_the_run_s_own_stages(monkeypatch: pytest.MonkeyPatch) -> None:
    built = _built_from_config(monkeypatch)
    seen = _scored_with(monkeypatch, UpscaleMetrics)
    metrics = _run(DEVICE)  # the default run: device preset, metrics=upscale
    assert {"upscale_psnr", "noise_psnr", "bicubic_psnr"} <= set(metrics)  # every stage was there to score with
    kinds = {path: type(obj) for path, obj in built.items()}
    assert [p for p, k in kinds.items() if k in (Sphere, Simulator, FSRCNN)] == ["scene", "source", "upscale"]
    assert not [p for p in built if p.startswith("metrics.")]  # nothing built inside the metrics node
    (scored,) = seen
    assert scored.scene is built["scene"] and scored.source is built["source"] and scored.upscaler is built["upscale"]


def test_the_3d_metrics_score_with_the_run_s_own_stages(monkeypatch: pytest.MonkeyPatch) -> None:
    built = _built_from_config(monkeypatch)
    seen = _scored_with(monkeypatch, Metrics3D)
    metrics = _run([*DEVICE, "upscale=bicubic", *THREE_D])
    assert "upscale_psnr" in metrics and "depth_rmse_fused_mm" in metrics  # scored on the upscaled grid
    assert [p for p, obj in built.items() if isinstance(obj, (Sphere, Simulator))] == ["scene", "source"]
    (scored,) = seen
    assert scored.scene is built["scene"] and scored.source is built["source"]


@pytest.mark.parametrize("option", ["full", "upscale"])
def test_the_metrics_nodes_hold_no_copy_of_another_stage(option: str) -> None:
    cfg, _ = compose([f"metrics={option}"])
    node = plain_config(cfg)["metrics"]
    assert not {"scene", "source", "upscaler"} & set(node)
    assert not any(isinstance(v, dict) for v in node.values())  # no nested _target_ node to build


def test_with_stages_hands_over_the_run_s_objects() -> None:
    scene, source, upscaler = Sphere(), Simulator(), object()
    stages = RunStages(scene, source, upscaler)  # type: ignore[arg-type]
    up = UpscaleMetrics().with_stages(stages)
    assert isinstance(UpscaleMetrics(), ScoresWithStages) and isinstance(Metrics3D(), ScoresWithStages)
    assert (up.scene, up.source, up.upscaler) == (scene, source, upscaler)
    assert up.scene is scene and up.source is source and up.upscaler is upscaler
    full = Metrics3D(sample_spacing_mm=2.0).with_stages(stages)
    assert full.scene is scene and full.source is source and full.sample_spacing_mm == 2.0


def test_noise_scores_switch_off_with_their_key() -> None:
    metrics = _run([*DEVICE, "metrics.noise_scores=false"])
    assert "upscale_psnr" in metrics and not any(k.startswith("noise_") for k in metrics)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=3, max_size=400),
    st.floats(-1e3, 1e3, allow_nan=False),
    st.sampled_from([1.0, 1e-9, 1e-14, 1e-17]),
)
def test_sample_skewness_is_scipy_s_to_the_bit(values: list[float], offset: float, spread: float) -> None:
    """The 3D metrics' skewness computes scipy.stats.skew's operations itself (1.3 ms of array-API
    wrapper a call saved): the same float64 bits, near-constant samples (scipy's NaN and its
    cancellation warning) included."""
    from scipy.stats import skew

    v = offset + spread * np.asarray(values)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = float(skew(v)) if np.std(v) > 0 else float("nan")
        got = sample_skewness(v)
    assert got == want or (np.isnan(got) and np.isnan(want))


def test_the_upscale_metrics_test_the_camera_s_content_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """One content test per scored image (camera, upscaled, noise-only, bicubic), and no raw
    SSIM of the noise-only score, which is not kept: at 27f888e the camera's test ran twice and
    the noise-only raw scores were computed and dropped (5 tests and 8 SSIMs a job)."""
    import nirspi_pipe.metrics as metrics
    import nirspi_pipe.upscale.metrics as upscale_metrics

    calls = {"content_test": 0, "ssim": 0}
    for name in calls:
        inner = getattr(metrics, name)

        def counted(*a: Any, _inner: Any = inner, _name: str = name, **kw: Any) -> Any:
            calls[_name] += 1
            return _inner(*a, **kw)

        for module in (metrics, upscale_metrics):  # also where a module imported the name (27f888e)
            monkeypatch.setattr(module, name, counted, raising=False)
    metrics_out = _run(DEVICE)
    assert {"ssim", "upscale_ssim", "noise_ssim", "bicubic_ssim"} <= set(metrics_out)
    assert calls == {"content_test": 4, "ssim": 7}


@settings(max_examples=200, deadline=None)
@given(
    st.integers(3, 40),
    st.integers(3, 40),
    st.integers(0, 2**32 - 1),
    st.sampled_from([1.0, 1e-6, 1e3]),
    st.sampled_from([1.0, 0.5]),
)
def test_ssim_is_scikit_image_s_to_the_bit(h: int, w: int, seed: int, scale: float, data_range: float) -> None:
    """The image metrics' SSIM runs scikit-image's operations itself (one filter call for the five
    window means): the same float64 bits as skimage.metrics.structural_similarity."""
    from skimage.metrics import structural_similarity

    from nirspi_pipe.metrics import ssim

    rng = np.random.default_rng(seed)
    a = rng.random((h, w)) * scale
    b = a + rng.normal(size=(h, w)) * scale * 0.1 if seed % 2 else rng.random((h, w))
    side = min(h, w)
    win = min(7, side if side % 2 == 1 else side - 1)
    if win < 3:
        assert np.isnan(ssim(a, b, data_range))
        return
    want = float(np.clip(structural_similarity(a, b, data_range=data_range, win_size=win), -1.0, 1.0))
    assert ssim(a, b, data_range) == want
    assert ssim(np.asfortranarray(a), b, data_range) == want
