"""Tests of the nirspi-admm example plugin: the solver itself, and its discovery by nirspi-pipe."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from nirspi_admm import ADMMTVSolver, admm_tv
from nirspi_admm.solver import _grad, _grad_adjoint

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.metrics import psnr, rmse, ssim
from nirspi_pipe.patterns.hadamard import fwht2, sylvester
from nirspi_pipe.patterns.synthetic import split_hadamard
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Acquisition, Camera


def low_sequency_indices(n: int, ratio: float) -> np.ndarray:
    """The ``ratio·n²`` patterns of lowest total sequency (rows + columns), a zig-zag-like order."""
    seq = (np.diff(sylvester(n), axis=1) != 0).sum(axis=1)
    total = (seq[:, None] + seq[None, :]).ravel()
    return np.argsort(total, kind="stable")[: int(round(ratio * n * n))].astype(np.int64)


def test_gradient_adjoint() -> None:
    rng = np.random.default_rng(1)
    x, g = rng.normal(size=(8, 8)), rng.normal(size=(2, 8, 8))
    assert np.isclose(np.sum(_grad(x) * g), np.sum(x * _grad_adjoint(g)))


def test_full_sampling_without_tv_is_exact() -> None:
    rng = np.random.default_rng(2)
    img = rng.uniform(size=(16, 16))
    idx = np.arange(256)
    out, info = admm_tv(16, idx, fwht2(img).ravel(), tv_weight=0.0, tol=1e-10, max_iter=50)
    assert np.allclose(out, img, atol=1e-6)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_beats_zero_filled_fwht_at_25_percent_on_the_sphere(noise: float) -> None:
    n = 64
    scene = Sphere().render(Camera(n))
    acq = Simulator(forward_model(noise_rel=noise)).acquire(
        scene, low_sequency_indices(n, 0.25), n, np.random.default_rng(0)
    )
    zero_filled = FWHTSolver().solve(acq).data
    admm = ADMMTVSolver(tv_weight=0.03).solve(acq)
    truth = scene.radiance
    assert admm.info["stop_reason"] == "converged"
    assert rmse(truth, admm.data) < 0.85 * rmse(truth, zero_filled)
    assert ssim(truth, admm.data) > ssim(truth, zero_filled)
    assert admm.data.min() >= 0.0


def test_bad_config() -> None:
    with pytest.raises(ConfigError, match="tv_weight"):
        ADMMTVSolver(tv_weight=-1.0)
    with pytest.raises(ConfigError, match="tv_weight"):
        ADMMTVSolver(tv_weight="sure")
    with pytest.raises(ConfigError, match="rho"):
        ADMMTVSolver(rho=0.0)


@pytest.mark.parametrize("kind", ["binary", "signed"])
def test_explicit_patterns_match_the_hadamard_path(kind: str) -> None:
    """Explicit patterns (the same Hadamard rows as a matrix, as ±1 or as their 0/1 positive
    halves) give the fast path's image at a fixed weight: the data term is scaled alike."""
    n = 16
    scene = Sphere().render(Camera(n))
    idx = low_sequency_indices(n, 0.5)
    h = np.kron(sylvester(n), sylvester(n)).astype(float)[idx]
    x = scene.radiance.ravel()
    fast = ADMMTVSolver(tv_weight=0.02, tol=1e-7, max_iter=2000).solve(Acquisition(n=n, indices=idx, y_pos=h @ x)).data
    p = h if kind == "signed" else (1.0 + h) / 2.0
    # 0/1 halves alone lose nothing only when the offset is known: keep the pairs (split) there
    acq = (
        Acquisition(n=n, indices=np.arange(len(idx)), y_pos=p @ x, patterns=p)
        if kind == "signed"
        else (Acquisition(n=n, indices=np.arange(len(idx)), y_pos=p @ x, y_neg=(1.0 - p) @ x, patterns=2 * p - 1))
    )
    explicit = ADMMTVSolver(tv_weight=0.02, tol=1e-7, max_iter=2000).solve(acq).data
    assert np.max(np.abs(explicit - fast)) < 1e-3


def test_discovered_by_nirspi_pipe() -> None:
    from nirspi_pipe.app.plugins import discover

    report = discover(refresh=True)
    names = {p.name: p for p in report.plugins}
    assert "admm" in names, report
    assert names["admm"].options.get("solver") == ["admm_tv"]
    assert not any(g.startswith("schema") for g in names["admm"].options)  # its schema is not an option


def test_the_config_takes_its_defaults_from_the_class() -> None:
    # admm_tv.yaml names only its _target_: every key comes from ADMMTVSolver's fields.
    from hydra import compose, initialize_config_module

    from nirspi_pipe.app.plugins import activate

    activate()  # plugin config folders join the search path
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["solver=admm_tv"])
    default = ADMMTVSolver()
    for key in ("tv_weight", "lam_floor", "rho", "max_iter", "tol", "nonneg"):
        assert cfg.solver[key] == getattr(default, key), key


def test_runs_through_nirspi_run(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("nirspi-run")
    out = tmp_path / "run"
    proc = subprocess.run(
        [str(exe), "solver=admm_tv", "scan.ratio=0.25", "camera.resolution=32", f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )
    assert proc.returncode == 0, proc.stderr
    record = json.loads((out / "record.json").read_text())
    assert record["meta"]["status"] == "ok"
    assert record["choices"]["solver"] == "admm_tv"
    assert record["info"]["solver"]["iterations"] >= 1


def _camera(n: int) -> np.ndarray:
    from skimage import data
    from skimage.transform import resize

    return resize(data.camera().astype(float) / 255.0, (n, n), anti_aliasing=True)


def test_default_weight_beats_the_pseudo_inverse_by_6_db_on_poisson_data() -> None:
    """Issue #15's case: camera image, 64², every split pattern, Poisson α = 100; SURE weight."""
    x = _camera(64)
    acq = split_hadamard(x, 100.0)
    base = psnr(x, FWHTSolver().solve(acq).data)
    out = ADMMTVSolver().solve(acq)
    assert out.info["lam_rule"] == "sure"
    assert psnr(x, out.data) - base >= 6.0


def test_noise_free_data_is_exact_at_default_settings() -> None:
    x = _camera(64)
    out = ADMMTVSolver().solve(split_hadamard(x))
    assert out.info["lam_rule"] == "exact"
    assert psnr(x, out.data) >= 60.0
