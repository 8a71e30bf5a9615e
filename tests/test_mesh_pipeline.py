"""The whole 3D path through run_pipeline and execute_job, with a test-only stand-in SFS stage."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from omegaconf import OmegaConf, open_dict

from nirspi_pipe.mesh.standin import degraded_depth
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Camera, DepthMap, Image2D


@dataclass(frozen=True)
class StandinSFS:
    """Test-only sfs stage: the default sphere's true depth, degraded to SFS-like relative depth
    (it re-renders the scene; a real SFS works from the image)."""

    seed: int = 0

    def solve(self, image: Image2D, camera: Camera) -> DepthMap:
        return degraded_depth(Sphere().render(camera), np.random.default_rng(self.seed))


@pytest.fixture(autouse=True)
def _standin_allowed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stand-in is a test class: put it on the target allow-list (nirspi_pipe.targets) here."""
    from nirspi_pipe import targets

    monkeypatch.setattr(targets, "PROJECT_TARGETS", targets.PROJECT_TARGETS | {f"{__name__}.StandinSFS"})


def _cfg(*overrides: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    with open_dict(cfg):
        cfg.sfs = OmegaConf.create({"_target_": f"{__name__}.StandinSFS"})
    return cfg


@pytest.mark.parametrize("surface", ["power_crust", "poisson"])
def test_3d_run(surface):
    from nirspi_pipe.pipeline import run_pipeline

    out = run_pipeline(_cfg("itof=cw4", "fusion=itof", f"surface={surface}", "metrics=full"))
    m = out.metrics
    for key in (
        "ssim",
        "depth_rmse_sfs_mm",
        "depth_rmse_fused_mm",
        "improvement_pct",
        "skewness_mean",
        "chamfer_mm",
        "hausdorff_mm",
    ):
        assert key in m and np.isfinite(m[key]), key
    assert {"sfs", "itof", "fusion", "surface", "metrics"} <= set(out.timings_ms)
    assert out.info["fusion"]["anchors_used"] == 4
    assert m["chamfer_mm"] < 10.0  # 1 cm iToF noise moves the whole patch by a few mm at most


def test_execute_job_writes_mesh_files(tmp_path):
    from nirspi_pipe.app.jobs import execute_job

    cfg = _cfg("itof=cw4", "fusion=itof", "surface=power_crust", "metrics=full")
    record = execute_job(cfg, tmp_path, {}, [])
    assert record["meta"]["status"] == "ok", record["meta"]["error"]
    assert (tmp_path / "mesh.ply").stat().st_size > 1000
    assert (tmp_path / "mesh.png").stat().st_size > 1000
    import pyvista as pv

    ply = pv.read(str(tmp_path / "mesh.ply"))
    assert ply.n_cells == record["info"]["surface"]["faces"]


def test_fusion_without_sfs_is_config_error():
    from hydra import compose, initialize_config_module

    from nirspi_pipe.errors import ConfigError
    from nirspi_pipe.pipeline import run_pipeline

    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["itof=cw4", "fusion=itof"])
    with pytest.raises(ConfigError, match="fusion"):
        run_pipeline(cfg)
