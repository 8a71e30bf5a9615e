"""The 2D path end to end, in-process: exactness, determinism, records."""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from conftest import NOISE_FREE
from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.physics.splitmeasure import split_measure
from nirspi_pipe.pipeline import run_pipeline
from nirspi_pipe.scene.objects import ImageTarget, Sphere
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera


def _cfg(overrides: list[str]):
    """The composed config of the noise-free scene plus ``overrides`` (later overrides win)."""
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        return compose("config", overrides=[*NOISE_FREE, *overrides])


@pytest.mark.parametrize("scene", ["sphere", "image"])
@pytest.mark.parametrize("resolution", [16, 64])
def test_noise_free_full_sampling_is_exact(scene: str, resolution: int) -> None:
    out = run_pipeline(_cfg([f"scene={scene}", f"camera.resolution={resolution}"]))
    truth = out.products.truth.radiance
    assert np.max(np.abs(out.products.image.data - truth)) < 1e-9
    assert out.metrics["rmse"] < 1e-9
    assert out.metrics["ssim"] > 0.999999
    assert set(out.timings_ms) >= {"scene", "scan", "source", "solver", "metrics", "total"}


def test_same_seed_same_numbers_and_seeds_differ() -> None:
    a = run_pipeline(_cfg(["source.effects.noise_rel=0.01", "seed=7", "camera.resolution=32"]))
    b = run_pipeline(_cfg(["source.effects.noise_rel=0.01", "seed=7", "camera.resolution=32"]))
    c = run_pipeline(_cfg(["source.effects.noise_rel=0.01", "seed=8", "camera.resolution=32"]))
    assert np.array_equal(a.products.image.data, b.products.image.data)
    assert a.metrics == b.metrics
    assert not np.array_equal(a.products.image.data, c.products.image.data)
    assert a.metrics["psnr"] < 200  # noise is really there


def test_undersampling_keeps_dc_and_mean() -> None:
    out = run_pipeline(_cfg(["scan.ratio=0.25", "camera.resolution=32"]))
    acq = out.products.acquisition
    assert len(acq.indices) == 256
    # zero-filled inverse keeps the measured coefficients exactly, so the mean (DC) is exact
    np.testing.assert_allclose(out.products.image.data.mean(), out.products.truth.radiance.mean())


def test_split_measurements_cancel_background() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((8, 8))
    idx = np.arange(64)
    y_pos, y_neg = split_measure(img, idx)
    np.testing.assert_allclose(y_pos - y_neg, fwht2(img).ravel())
    np.testing.assert_allclose(y_pos + y_neg, img.sum())  # complementary pair sums to all-on
    assert np.all(y_pos >= -1e-12) and np.all(y_neg >= -1e-12)  # 0/1 patterns: non-negative


def test_sphere_geometry() -> None:
    cam = Camera(resolution=64, fov_deg=20.0)
    s = Sphere(distance_mm=200.0, diameter_mm=50.0, reflectance=0.5).render(cam)
    # Apparent radius: asin(r/d) of the half field of view tan(10°)
    expected_px = np.tan(np.arcsin(25 / 200)) / np.tan(np.deg2rad(10)) * 32
    assert abs(np.sqrt(s.coverage.sum() / np.pi) - expected_px) < 0.5
    assert np.isclose(np.nanmin(s.depth_m[s.mask]), 0.175, atol=1e-3)  # front of the sphere
    assert np.all(s.radiance <= 0.5 + 1e-12) and s.radiance.max() > 0.49  # R·cos, cos ≈ 1 at centre
    assert np.all(np.isinf(s.depth_m[s.coverage == 0]))
    # anti-aliased edge: some pixels are partially covered
    assert np.any((s.coverage > 0) & (s.coverage < 1))


def test_image_target_fills_view() -> None:
    cam = Camera(resolution=32)
    s = ImageTarget().render(cam)
    assert s.mask.all()
    np.testing.assert_allclose(s.depth_m, 0.2)
    assert 0 < s.radiance.mean() < 0.8


def test_simulator_rejects_mismatched_scene() -> None:
    from nirspi_pipe.errors import NirspiError

    scene = Sphere().render(Camera(resolution=16))
    with pytest.raises(NirspiError):
        Simulator().acquire(scene, np.arange(64), 8, np.random.default_rng(0))


class _SolverWithoutSolve:
    """A solver stage that lacks the one method the pipeline calls (test only)."""

    def reconstruct(self, acquisition: object) -> None: ...


def test_a_stage_without_its_protocols_members_fails_when_built(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every stage is checked against its group's protocol (nirspi_pipe.stages.PROTOCOLS) when
    it is built: one line naming the group's target and the missing member, before any stage runs."""
    from nirspi_pipe import targets
    from nirspi_pipe.errors import ConfigError
    from nirspi_pipe.instantiate import plain_config
    from nirspi_pipe.pipeline import build_stages
    from nirspi_pipe.stages import PROTOCOLS, protocol_members

    target = f"{__name__}._SolverWithoutSolve"
    monkeypatch.setattr(targets, "PROJECT_TARGETS", targets.PROJECT_TARGETS | {target})
    cfg = {"solver": {"_target_": target}}
    with pytest.raises(ConfigError) as err:
        build_stages(cfg)
    assert str(err.value).count("\n") == 0
    assert str(err.value).startswith(f"solver._target_='{target}' is not allowed")
    assert str(err.value).endswith("it lacks solve")
    # every shipped stage of the default run and the 3D chain has its protocol's members
    built = build_stages(plain_config(_cfg(["sfs=lax_friedrichs", "itof=cw4", "fusion=itof", "surface=poisson"])))
    assert set(built) == set(PROTOCOLS)
    assert protocol_members(PROTOCOLS["source"]) == ["needs_scene", "acquire"]
