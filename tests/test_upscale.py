"""Super-resolution (``upscale`` group): shapes, the numpy layers against reference loops,
the shipped weights, hard inputs, config errors and the pipeline wiring. All fast."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from omegaconf import OmegaConf

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.metrics import psnr
from nirspi_pipe.pipeline import build, run_pipeline
from nirspi_pipe.types import Image2D
from nirspi_pipe.upscale import FSRCNN, Bicubic, bicubic, block_mean
from nirspi_pipe.upscale.data import heldout_pairs, spi_lowres
from nirspi_pipe.upscale.fsrcnn import (
    ConvLayer,
    FsrcnnWeights,
    conv2d,
    conv_transpose2d,
    fsrcnn_forward,
    load_weights,
    packaged_weights_path,
    save_weights,
)

SCALES = (2, 3, 4)


def _cfg(overrides: list[str]):
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        return compose("config", overrides=overrides)


# --- reference implementations by direct loops --------------------------------------------


def _conv_loops(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    co, ci, k, _ = w.shape
    p = k // 2
    _, h, wd = x.shape
    xp = np.zeros((ci, h + 2 * p, wd + 2 * p))
    xp[:, p : p + h, p : p + wd] = x
    out = np.zeros((co, h, wd))
    for o in range(co):
        for i in range(h):
            for j in range(wd):
                out[o, i, j] = b[o] + np.sum(w[o] * xp[:, i : i + k, j : j + k])
    return out


def _deconv_loops(x: np.ndarray, w: np.ndarray, b: np.ndarray, s: int, pad: int, opad: int) -> np.ndarray:
    ci, co, k, _ = w.shape
    _, h, wd = x.shape
    oh, ow = (h - 1) * s - 2 * pad + k + opad, (wd - 1) * s - 2 * pad + k + opad
    out = np.tile(b[:, None, None], (1, oh, ow)).astype(np.float64)
    for c in range(ci):
        for i in range(h):
            for j in range(wd):
                for ky in range(k):
                    for kx in range(k):
                        y, z = i * s - pad + ky, j * s - pad + kx
                        if 0 <= y < oh and 0 <= z < ow:
                            out[:, y, z] += x[c, i, j] * w[c, :, ky, kx]
    return out


def _tiny_net(
    rng: np.random.Generator, scale: int, d: int = 3, s: int = 2, m: int = 1, residual: bool = False
) -> FsrcnnWeights:
    shapes = [(d, 1, 5), (s, d, 1)] + [(s, s, 3)] * m + [(d, s, 1)]
    layers = tuple(
        ConvLayer(
            rng.normal(0, 0.5, (o, i, k, k)).astype(np.float32),
            rng.normal(0, 0.1, o).astype(np.float32),
            rng.uniform(0.0, 0.5, o).astype(np.float32),
        )
        for o, i, k in shapes
    )
    return FsrcnnWeights(
        scale,
        layers,
        rng.normal(0, 0.2, (d, 1, 9, 9)).astype(np.float32),
        np.array([0.1], np.float32),
        residual=residual,
        border=4 + m,
    )


def _forward_loops(lr: np.ndarray, net: FsrcnnWeights) -> np.ndarray:
    pad, s = net.border, net.scale
    x = np.pad(lr, pad, mode="symmetric")[None].astype(np.float64)
    for layer in net.layers:
        x = _conv_loops(x, layer.w.astype(np.float64), layer.b.astype(np.float64))
        x = np.where(x > 0, x, layer.alpha[:, None, None] * x)
    y = _deconv_loops(x, net.deconv_w.astype(np.float64), net.deconv_b.astype(np.float64), s, 4, s - 1)[0]
    h, w = lr.shape
    y = y[pad * s : pad * s + h * s, pad * s : pad * s + w * s]
    return y + bicubic(lr, s) if net.residual else y


# --- numpy layers -------------------------------------------------------------------------


@pytest.mark.parametrize("k", [1, 3, 5])
def test_conv2d_matches_loops(k: int) -> None:
    rng = np.random.default_rng(k)
    x, w, b = rng.normal(size=(3, 6, 7)), rng.normal(size=(4, 3, k, k)), rng.normal(size=4)
    np.testing.assert_allclose(conv2d(x, w, b), _conv_loops(x, w, b), atol=1e-12)


@pytest.mark.parametrize("scale", SCALES)
def test_conv_transpose_matches_loops(scale: int) -> None:
    rng = np.random.default_rng(scale)
    x, w, b = rng.normal(size=(3, 4, 5)), rng.normal(size=(3, 2, 9, 9)), rng.normal(size=2)
    out = conv_transpose2d(x, w, b, scale, 4, scale - 1)
    assert out.shape == (2, 4 * scale, 5 * scale)
    np.testing.assert_allclose(out, _deconv_loops(x, w, b, scale, 4, scale - 1), atol=1e-12)


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("residual", [False, True])
def test_forward_matches_loop_reference_on_tiny_network(scale: int, residual: bool) -> None:
    rng = np.random.default_rng(10 * scale + residual)
    net = _tiny_net(rng, scale, residual=residual)
    lr = rng.uniform(0, 1, (5, 6))
    # float64 arithmetic end to end (float32 differed by ~1e-7 between OpenBLAS kernel sets and
    # moved the 3D tables, issue 12): the loops in float64 agree to rounding
    np.testing.assert_allclose(fsrcnn_forward(lr, net), _forward_loops(lr, net), rtol=1e-12, atol=1e-12)


def test_save_load_round_trip(tmp_path: Path) -> None:
    net = _tiny_net(np.random.default_rng(0), 3, residual=True)
    save_weights(tmp_path / "w.npz", net)
    back = load_weights(3, tmp_path / "w.npz")
    lr = np.random.default_rng(1).uniform(0, 1, (6, 6))
    np.testing.assert_array_equal(fsrcnn_forward(lr, back), fsrcnn_forward(lr, net))
    with pytest.raises(ConfigError, match="weights"):
        load_weights(2, tmp_path / "w.npz")  # trained for ×3


# --- shipped weights ---------------------------------------------------------------------


@pytest.mark.parametrize("scale", SCALES)
def test_packaged_weights_load_and_are_small(scale: int) -> None:
    path = packaged_weights_path(scale)
    assert path.is_file() and path.parent.name == "weights" and path.parent.parent.name == "upscale"
    assert path.stat().st_size < 100_000
    net = load_weights(scale)
    assert net.scale == scale and net.n_params < 20_000
    assert all(l.w.dtype == np.float32 and np.all(np.isfinite(l.w)) for l in net.layers)
    assert net.meta and net.meta["trained_by"] == "nirspi-train-fsrcnn"


def test_packaged_weights_load_in_a_fresh_interpreter(tmp_path: Path) -> None:
    code = (
        "from nirspi_pipe.upscale.fsrcnn import load_weights, packaged_weights_path;"
        "print(packaged_weights_path(4)); print(load_weights(4).n_params)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert int(out.stdout.split()[-1]) > 0


@pytest.mark.parametrize("scale", SCALES)
def test_fsrcnn_beats_bicubic_on_a_heldout_image(scale: int) -> None:
    pair = heldout_pairs(scale, 0.0, n_lr=64, n_shapes=0)[0]  # camera man, never trained on
    assert pair.name == "camera"
    bic = np.clip(bicubic(pair.lr, scale), 0, 1)
    net = FSRCNN(scale=scale).upscale(Image2D(pair.lr)).data
    assert psnr(pair.hr, net) > psnr(pair.hr, bic)


# --- shapes and hard inputs --------------------------------------------------------------


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("shape", [(16, 16), (8, 12), (1, 1), (3, 2)])
def test_output_shapes(scale: int, shape: tuple[int, int]) -> None:
    img = Image2D(np.random.default_rng(0).uniform(0, 1, shape))
    for stage in (Bicubic(scale=scale), FSRCNN(scale=scale)):
        out = stage.upscale(img)
        assert out.data.shape == (shape[0] * scale, shape[1] * scale)
        assert out.info["scale"] == scale and out.info["model"] in ("bicubic", "fsrcnn")


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("value", [0.0, 0.3, 0.8, 1.0])
def test_constant_images_stay_close_to_constant(scale: int, value: float) -> None:
    img = Image2D(np.full((8, 8), value))
    np.testing.assert_allclose(Bicubic(scale=scale).upscale(img).data, value, atol=1e-12)
    out = FSRCNN(scale=scale).upscale(img).data
    assert np.all(np.isfinite(out)) and np.all((out >= 0) & (out <= 1))
    assert abs(out.mean() - value) < 0.02


@settings(max_examples=25, deadline=None)
@given(
    arrays(
        np.float64, st.tuples(st.integers(1, 10), st.integers(1, 10)), elements=st.floats(-1e3, 1e3, allow_nan=False)
    ),
    st.sampled_from(SCALES),
)
def test_any_finite_input_gives_finite_clipped_output(data: np.ndarray, scale: int) -> None:
    for stage in (Bicubic(scale=scale), FSRCNN(scale=scale)):
        out = stage.upscale(Image2D(data)).data
        assert np.all(np.isfinite(out)) and out.min() >= 0.0 and out.max() <= 1.0


def test_non_finite_input_warns_and_stays_finite() -> None:
    data = np.full((8, 8), 0.5)
    data[2, 3], data[5, 5] = np.nan, np.inf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = FSRCNN(scale=2).upscale(Image2D(data)).data
    assert np.all(np.isfinite(out))
    assert any("non-finite" in str(w.message) for w in caught)


def test_inputs_are_not_modified() -> None:
    data = np.random.default_rng(3).uniform(0, 1, (8, 8))
    copy = data.copy()
    for stage in (Bicubic(scale=3), FSRCNN(scale=3)):
        stage.upscale(Image2D(data))
    np.testing.assert_array_equal(data, copy)


def test_lowres_degradation_is_the_block_mean_when_noise_free() -> None:
    hr = np.random.default_rng(0).uniform(0, 1, (48, 48))
    lr = spi_lowres(hr, 3, 0.0, np.random.default_rng(1))
    np.testing.assert_allclose(lr, block_mean(hr, 3), atol=1e-12)


# --- configuration -----------------------------------------------------------------------


@pytest.mark.parametrize("bad", [1, 5, 0, -2, 2.5, "2", True])
def test_bad_scale_names_the_key(bad: object) -> None:
    for target in ("nirspi_pipe.upscale.FSRCNN", "nirspi_pipe.upscale.Bicubic"):
        node = OmegaConf.create({"_target_": target, "scale": bad})
        with pytest.raises(ConfigError) as info:
            build(node, "upscale")
        assert info.value.key == "upscale.scale"
        assert "\n" not in str(info.value)


def test_missing_weights_file_names_the_key() -> None:
    node = OmegaConf.create({"_target_": "nirspi_pipe.upscale.FSRCNN", "scale": 2, "weights": "/no/such.npz"})
    with pytest.raises(ConfigError) as info:
        build(node, "upscale")
    assert info.value.key == "upscale.weights"


# --- pipeline wiring ---------------------------------------------------------------------


@pytest.mark.parametrize("scale", SCALES)
def test_pipeline_fsrcnn_with_upscale_metrics(scale: int) -> None:
    out = run_pipeline(_cfg(["upscale=fsrcnn", f"upscale.scale={scale}", "metrics=upscale", "camera.resolution=32"]))
    assert out.products.upscaled.data.shape == (32 * scale, 32 * scale)
    assert out.info["upscale"]["model"] == "fsrcnn" and out.info["upscale"]["scale"] == scale
    m = out.metrics
    assert {"psnr", "upscale_psnr", "bicubic_psnr", "upscale_gain_db", "upscale_ssim"} <= set(m)
    assert np.isfinite(m["upscale_psnr"]) and 15 < m["upscale_psnr"] < 80
    assert "upscale" in out.timings_ms


def test_one_way_to_switch_upscale_off(tmp_path: Path) -> None:
    """``upscale=null`` (rewritten to ``off`` by nirspi-run) and ``upscale=off`` are one thing:
    the same record, timings and dates aside; ``upscale=none`` is no option (one line)."""
    from nirspi_pipe.app.api import compose as compose_job
    from nirspi_pipe.app.validate import check_overrides, rewrite_nulls
    from nirspi_pipe.execute import execute_job

    records = []
    for arg in ("upscale=null", "upscale=off"):
        (args,), problem = rewrite_nulls([arg])
        assert problem is None
        cfg, choices = compose_job(["camera.resolution=8", args])
        rec = execute_job(cfg, tmp_path / arg, {k: str(v) for k, v in choices.items()}, [arg])
        for volatile in ("started", "wall_s"):
            rec["meta"].pop(volatile)
        rec.pop("timings_ms")
        records.append(rec)
    assert records[0]["meta"]["status"] == "ok" and records[0]["config"]["upscale"] is None
    records[0]["meta"]["overrides"] = records[1]["meta"]["overrides"]  # what was typed differs
    assert records[0] == records[1]
    problem = check_overrides(["upscale=none"])
    assert problem is not None and problem.startswith("upscale=none is not an option") and "\n" not in problem


def test_upscale_metrics_on_exact_reconstruction_match_bicubic_of_the_truth() -> None:
    # Noise-free, full sampling: the reconstruction is the truth, so bicubic_* scores plain
    # interpolation of the camera image against the fine render; upscale=bicubic must match it.
    out = run_pipeline(_cfg(["upscale=bicubic", "upscale.scale=2", "metrics=upscale", "camera.resolution=32"]))
    assert out.metrics["upscale_psnr"] == pytest.approx(out.metrics["bicubic_psnr"], abs=1e-9)
    assert out.metrics["upscale_gain_db"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.slow
def test_cli_bad_scale_is_one_line(tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "nirspi-run"
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    res = subprocess.run(
        [str(exe), "upscale=fsrcnn", "upscale.scale=5"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "upscale.scale=5" in lines[0]


@pytest.mark.slow
@pytest.mark.torch
def test_train_command_smoke(tmp_path: Path) -> None:
    from nirspi_pipe.upscale.train import main

    assert main(["--scales", "3", "--iters", "3", "--variants", "1", "--batch", "4", "--out", str(tmp_path)]) == 0
    net = load_weights(3, tmp_path / "fsrcnn_x3.npz")
    assert net.residual and net.meta["iters"] == 3 and net.meta["numpy_vs_torch_max_abs"] < 1e-4
    assert {r["noise_rel"] for r in net.meta["heldout"]} == {0.0, 1e-3}


def test_remembered_noise_free_images_give_the_same_scores() -> None:
    """The upscale metrics remember the source's image of the fine scene and the upscaled
    noise-free image across jobs (issue 42 item 6): a job after others (cache warm, seeds and
    scan orders that share them) scores exactly as the same job alone (cache empty), and a
    job of another scene or light level is not given their images."""
    from nirspi_pipe.scene.render import forget_renders
    from nirspi_pipe.upscale import metrics as um

    base = ["upscale=fsrcnn", "upscale.scale=2", "metrics=upscale", "camera.resolution=16"]
    jobs = [
        [*base, "seed=1"],
        [*base, "seed=2", "scan=hilbert"],
        [*base, "seed=1", "scene=torus"],
        [*base, "seed=1", "illumination=klux", "illumination.klux=30"],
    ]
    um._REMEMBERED.clear()
    warm = [run_pipeline(_cfg(job)).metrics for job in jobs]
    assert 2 <= len(um._REMEMBERED) <= um.MAX_REMEMBERED
    assert all(not value.flags.writeable for _anchor, value in um._REMEMBERED.values())
    for job, scores in zip(jobs, warm, strict=True):
        um._REMEMBERED.clear()
        forget_renders()
        alone = run_pipeline(_cfg(job)).metrics
        assert alone.keys() == scores.keys()
        for key in alone:
            assert np.array_equal(alone[key], scores[key], equal_nan=True), (job, key)
    assert warm[0]["noise_psnr"] != warm[2]["noise_psnr"]  # another scene: not the torus's images


def test_remembered_value_needs_its_anchor() -> None:
    """A remembered image keyed by an object's identity is computed again for another object."""
    from nirspi_pipe.upscale import metrics as um

    um._REMEMBERED.clear()
    a, b = object(), object()
    calls: list[int] = []

    def make() -> np.ndarray:
        calls.append(1)
        return np.zeros(3)

    um._remembered(("k", 1), a, make)
    um._remembered(("k", 1), a, make)
    assert len(calls) == 1
    um._remembered(("k", 1), b, make)
    assert len(calls) == 2
    um._remembered(("k", [1]), None, make)  # unhashable: computed each time, never kept
    um._remembered(("k", [1]), None, make)
    assert len(calls) == 4 and len(um._REMEMBERED) == 1
    um._REMEMBERED.clear()
