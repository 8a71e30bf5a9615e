"""FSRCNN ×4 for the paper's device (issue 11, must-have 1): the shipped ``fsrcnn_x4_led8.npz``,
trained on 8² SPI reconstructions with the device's noise levels, selected by ``preset=device``
and scored against bicubic on held-out data the training never saw. Numpy only (no torch); a few
seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.pipeline import build
from nirspi_pipe.types import Image2D
from nirspi_pipe.upscale.data import HELDOUT_SAMPLES, TRAIN_SAMPLES
from nirspi_pipe.upscale.evaluate import score_heldout, summarise
from nirspi_pipe.upscale.fsrcnn import FSRCNN, load_weights, resolve_weights, shipped_weights

DEVICE_WEIGHTS = "fsrcnn_x4_led8.npz"
#: The device's noise expressed as ``noise_rel`` of :func:`nirspi_pipe.upscale.data.spi_lowres`:
#: 0.028–0.040 measured on the default run and on Figure 9's settings, 5–50 kLux (docs/upscale.md).
DEVICE_NOISE_REL = 0.03
#: Margin the shipped device weights must keep over bicubic, mean PSNR over the 10 held-out
#: images (dB). The measured gains are in the file's meta and docs/upscale.md; the margin is
#: below them so that a rebuild on another BLAS still passes, and above 0 so that a network that
#: does no better than bicubic fails.
MARGIN_DB = {0.0: 0.2, DEVICE_NOISE_REL: 0.1}
#: No single held-out image may lose more than this to bicubic (dB). The mean gain comes mostly
#: from the spheres; on the natural photographs without noise the network loses up to 0.72 dB
#: (astronaut; docs/upscale.md), so this floor states how much a single image may lose.
WORST_IMAGE_DB = -1.0


def _cfg(overrides: list[str]):
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        return compose("config", overrides=overrides)


def test_device_weights_are_shipped_and_trained_for_the_device() -> None:
    assert DEVICE_WEIGHTS in shipped_weights()
    path = resolve_weights(4, DEVICE_WEIGHTS)
    assert path.is_file() and path.parent == resolve_weights(4).parent and path.stat().st_size < 100_000
    w = load_weights(4, DEVICE_WEIGHTS)
    meta = w.meta or {}
    assert w.scale == 4 and w.residual  # a correction to bicubic (docs/upscale.md)
    assert meta["n_lr"] == 8 and meta["whole_images"] and meta["numpy_vs_torch_max_abs"] < 1e-4
    assert not set(meta["train_samples"]) & set(meta["heldout_samples"])
    assert tuple(meta["heldout_samples"]) == HELDOUT_SAMPLES and tuple(meta["train_samples"]) == TRAIN_SAMPLES
    # the 64²-trained file stays the default of upscale=fsrcnn
    assert load_weights(4).meta["n_lr"] == 64


def test_device_preset_selects_the_device_weights_and_fsrcnn_keeps_the_64_ones() -> None:
    dev = build(_cfg(["preset=device"]).upscale, "upscale")
    assert isinstance(dev, FSRCNN) and dev.weights == DEVICE_WEIGHTS and dev.scale == 4
    study = build(_cfg(["~preset", "upscale=fsrcnn", "upscale.scale=4"]).upscale, "upscale")
    assert isinstance(study, FSRCNN) and study.weights is None


def test_device_weights_beat_bicubic_on_the_heldout_device_set() -> None:
    """Held-out images (camera, astronaut, coins, moon, the paper's sphere at 200 and 150 mm, 4
    synthetic scenes of an unused seed) seen by an 8 × 8 SPI camera, noise-free and at the
    device's noise: FSRCNN's mean PSNR beats bicubic's by at least MARGIN_DB, no image loses more
    than WORST_IMAGE_DB, and the scores
    recorded in the file's meta at training time are reproduced by the numpy inference."""
    w = load_weights(4, DEVICE_WEIGHTS)
    noise = tuple(MARGIN_DB)
    rows = score_heldout(w, noise, n_lr=8)
    summary = {row["noise_rel"]: row for row in summarise(rows)}
    recorded = {row["noise_rel"]: row for row in (w.meta or {})["heldout"]}
    worst = min(rows, key=lambda r: r["gain_db"])
    assert worst["gain_db"] >= WORST_IMAGE_DB, worst
    for nr, margin in MARGIN_DB.items():
        row = summary[nr]
        assert row["images"] == 10
        assert row["gain_db"] >= margin, f"noise_rel={nr}: gain {row['gain_db']:+.2f} dB < {margin} dB"
        assert row["psnr_fsrcnn"] == pytest.approx(recorded[nr]["psnr_fsrcnn"], abs=0.02)
        assert row["psnr_bicubic"] == pytest.approx(recorded[nr]["psnr_bicubic"], abs=1e-6)


def test_unknown_weights_name_is_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="weights") as err:
        load_weights(4, "fsrcnn_x4_nope.npz")
    assert DEVICE_WEIGHTS in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="scale 2"):
        load_weights(2, DEVICE_WEIGHTS)  # a shipped ×4 file asked for ×2


def test_a_shipped_name_is_never_taken_from_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 24: a file in the working directory under a shipped name does not shadow the
    package's weights; ``./name`` asks for it explicitly. The record names the file and hash."""
    import hashlib

    monkeypatch.chdir(tmp_path)
    (tmp_path / DEVICE_WEIGHTS).write_bytes(resolve_weights(3).read_bytes())  # a ×3 file under the ×4 name
    packaged = resolve_weights(4, DEVICE_WEIGHTS)
    assert packaged.parent == resolve_weights(4).parent and packaged != tmp_path / DEVICE_WEIGHTS
    assert load_weights(4, DEVICE_WEIGHTS).scale == 4  # the package's ×4, not the ×3 impostor
    explicit = f"./{DEVICE_WEIGHTS}"
    assert resolve_weights(4, explicit) == Path(explicit)
    with pytest.raises(ConfigError, match="×3"):
        load_weights(4, explicit)
    assert np.isfinite(load_weights(3, explicit).deconv_w).all()
    info = FSRCNN(scale=4, weights=DEVICE_WEIGHTS).upscale(Image2D(np.full((8, 8), 0.5))).info
    assert info["weights_file"] == f"package:{DEVICE_WEIGHTS}"
    assert info["weights_sha256"] == hashlib.sha256(packaged.read_bytes()).hexdigest()
    info = FSRCNN(scale=3, weights=explicit).upscale(Image2D(np.full((8, 8), 0.5))).info
    assert info["weights_file"] == str((tmp_path / DEVICE_WEIGHTS).resolve())


@pytest.mark.slow
@pytest.mark.torch
def test_train_command_whole_image_mode_smoke(tmp_path: Path) -> None:
    """``--n-lr 8``: whole 8² images mirrored by the border, as at inference; the numpy forward
    reproduces the trained network and the held-out scores are at the requested noise levels."""
    from nirspi_pipe.upscale.train import main

    args = [
        "--scales",
        "4",
        "--n-lr",
        "8",
        "--iters",
        "3",
        "--variants",
        "1",
        "--shapes",
        "2",
        "--spheres",
        "1",
        "--batch",
        "4",
        "--noise-max",
        "0.06",
        "--noise-min",
        "0.01",
        "--heldout-noise",
        "0",
        "0.03",
        "--threads",
        "1",
        "--name",
        "w_x{scale}.npz",
        "--out",
        str(tmp_path),
    ]
    assert main(args) == 0
    net = load_weights(4, tmp_path / "w_x4.npz")
    meta = net.meta or {}
    assert meta["whole_images"] and meta["patch_lr"] == 8 and meta["train_images"] == len(TRAIN_SAMPLES) + 3
    assert meta["numpy_vs_torch_max_abs"] < 1e-4
    assert {r["noise_rel"] for r in meta["heldout"]} == {0.0, 0.03}


def test_equivalent_noise_rel_recovers_the_noise_of_spi_lowres() -> None:
    from nirspi_pipe.upscale.base import block_mean
    from nirspi_pipe.upscale.data import equivalent_noise_rel, sphere_hr, spi_lowres

    hr = sphere_hr(32, 200.0, 50.0, 0.8)
    for nr in (0.01, 0.03):
        est = [
            equivalent_noise_rel(spi_lowres(hr, 4, nr, np.random.default_rng(s)), block_mean(hr, 4)) for s in range(20)
        ]
        assert np.mean(est) == pytest.approx(nr, rel=0.15)  # a 64-pixel std: ~9 % per image
    assert equivalent_noise_rel(block_mean(hr, 4), block_mean(hr, 4)) < 1e-12


@pytest.mark.parametrize("klux", [5, 50])
def test_the_devices_noise_lies_inside_the_training_range(klux: int) -> None:
    """The device run under Figure 9's settings (noise, daylight wander, fog fluctuation) has an
    error equivalent to a noise_rel inside the range the device weights were trained on."""
    from nirspi_pipe.pipeline import run_pipeline
    from nirspi_pipe.upscale.data import equivalent_noise_rel

    meta = load_weights(4, DEVICE_WEIGHTS).meta or {}
    out = run_pipeline(_cfg(["+experiment=figure9", f"illumination.klux={klux}", "scene=sphere", "seed=0"]))
    nr = equivalent_noise_rel(out.products.image.data, out.products.acquisition.reference)
    assert meta["noise_min"] < nr < meta["noise_max"]
    assert nr == pytest.approx(DEVICE_NOISE_REL, rel=0.4)
