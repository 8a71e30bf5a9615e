"""source=stream against nirspi-device-emulator on loopback, protocol errors, and the converter."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.app.jobs import execute_job
from nirspi_pipe.device.convert import convert
from nirspi_pipe.device.emulator import Emulator
from nirspi_pipe.device.protocol import StreamError
from nirspi_pipe.device.recording import load_recording, save_recording
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import fwht2, sylvester
from nirspi_pipe.pipeline import run_pipeline
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sources.recorded import recording_to_acquisition
from nirspi_pipe.sources.stream import Stream
from nirspi_pipe.types import Camera


def sphere(n: int) -> np.ndarray:
    return Sphere().render(Camera(n)).radiance


def config(*overrides: str):
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_stream_from_the_emulator_reconstructs_the_scene() -> None:
    n = 32
    img = sphere(n)
    emu = Emulator(img, gain=2.5, background=7.0, noise_rel=0.0, device="test-emulator")
    port, thread = emu.serve_in_thread(connections=1, lifetime_s=30)
    out = run_pipeline(config("source=stream", f"source.port={port}", f"camera.resolution={n}"))
    thread.join(timeout=10)
    assert not thread.is_alive()
    acq = out.products.acquisition
    assert acq.info["device"] == "test-emulator" and acq.info["frames"] == n * n
    assert acq.gain == 2.5 and acq.y_neg is not None
    assert np.abs(out.products.image.data - img).max() < 1e-9  # background cancels in the split
    assert np.all(np.diff(acq.timestamps_s) > 0)


def test_stream_honours_the_scan_order_and_ratio() -> None:
    n = 16
    img = sphere(n)
    emu = Emulator(img, noise_rel=0.01, seed=3)
    port, thread = emu.serve_in_thread(connections=1, lifetime_s=30)
    out = run_pipeline(config("source=stream", f"source.port={port}", f"camera.resolution={n}", "scan.ratio=0.5"))
    thread.join(timeout=10)
    acq = out.products.acquisition
    assert np.array_equal(acq.indices, np.arange(n * n // 2))
    noisy = acq.coefficients() - fwht2(img).ravel()[: n * n // 2]
    assert 0 < np.std(noisy) < 0.1 * np.abs(fwht2(img)).max()


@pytest.mark.parametrize(
    "fault,field",
    [
        ("truncate", "frames"),
        ("nan", "y_pos"),
        ("bad-header", "header"),
        ("seq", "seq"),
        ("no-end", "end"),
        ("stall", "frames"),
    ],
)
def test_protocol_errors_name_the_field_and_record_no_result(tmp_path: Path, fault: str, field: str) -> None:
    n = 8
    emu = Emulator(sphere(n), fault=fault, io_timeout_s=1.5)
    port, thread = emu.serve_in_thread(connections=1, lifetime_s=30)
    cfg = config("source=stream", f"source.port={port}", f"camera.resolution={n}", "source.timeout_s=0.5")
    rec = execute_job(cfg, tmp_path, {"source": "stream"}, [])
    thread.join(timeout=10)
    err = rec["meta"]["error"]
    assert rec["meta"]["status"] == "failed" and f"stream field '{field}'" in err and "\n" not in err, err
    assert not (tmp_path / "arrays.npz").exists() and not rec["metrics"]
    if fault == "stall":
        assert "timed out" in err and "timeout_s=0.5" in err
    if fault == "truncate":
        assert "truncated" in err


def test_refused_request_and_closed_port() -> None:
    emu = Emulator(sphere(8))
    port, thread = emu.serve_in_thread(connections=1, lifetime_s=30)
    with pytest.raises(StreamError, match="field 'error'.*not 16"):
        Stream(port=port, timeout_s=5).acquire(None, np.arange(10), 16, np.random.default_rng(0))
    thread.join(timeout=10)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    with pytest.raises(StreamError, match="field 'connect'"):
        Stream(port=free, timeout_s=1).acquire(None, np.arange(4), 2, np.random.default_rng(0))
    with pytest.raises(ConfigError, match="port"):
        Stream()
    with pytest.raises(ConfigError, match="timeout_s"):
        Stream(port=1234, timeout_s=0)


@pytest.mark.slow  # end-to-end through two installed console scripts (10 s of CPU)
def test_emulator_console_script_and_nirspi_run(tmp_path: Path) -> None:
    bindir = Path(sys.executable).parent
    env = {**os.environ, "MPLBACKEND": "Agg"}
    with subprocess.Popen(
        [str(bindir / "nirspi-device-emulator"), "--resolution", "16", "--background", "3", "--lifetime-s", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    ) as emu:
        try:
            hello = json.loads(emu.stdout.readline())
            assert hello["host"] == "127.0.0.1" and hello["n"] == 16
            out = tmp_path / "run"
            run = subprocess.run(
                [
                    str(bindir / "nirspi-run"),
                    "source=stream",
                    f"source.port={hello['port']}",
                    "camera.resolution=16",
                    f"hydra.run.dir={out}",
                ],
                capture_output=True,
                text=True,
                env=env,
                timeout=300,
            )
            assert run.returncode == 0, run.stderr
            assert emu.wait(timeout=30) == 0  # served its one connection and stopped by itself
            with np.load(out / "arrays.npz") as arrs:
                assert np.abs(arrs["reconstruction"] - sphere(16)).max() < 1e-9
            rec = json.loads((out / "record.json").read_text())
            assert rec["info"]["source"]["frames"] == 256
        finally:
            if emu.poll() is None:  # a failed assertion: do not wait for its lifetime
                emu.kill()


# --- converter ---------------------------------------------------------------------------------


def _hadamard_rows(n: int, k: np.ndarray) -> np.ndarray:
    h = sylvester(n)
    return (h[k // n][:, :, None] * h[k % n][:, None, :]).reshape(len(k), n * n)


@pytest.mark.parametrize("form", ["pos_neg", "interleaved", "differential", "pos_neg_binary_halves"])
def test_convert_split_measurements_to_the_spec(tmp_path: Path, form: str) -> None:
    n = 16
    img = sphere(n)
    rng = np.random.default_rng(7)
    k = rng.permutation(n * n)[:100]
    pm = _hadamard_rows(n, k) * np.where(rng.random(100) < 0.3, -1.0, 1.0)[:, None]  # some rows stored negated
    pos, neg = ((1 + pm) / 2) @ img.ravel() + 1.0, ((1 - pm) / 2) @ img.ravel() + 1.0
    if form == "pos_neg":
        arrays = convert(pm, pos=pos, neg=neg, image=img)
    elif form == "pos_neg_binary_halves":
        arrays = convert((1 + pm) / 2, pos=pos, neg=neg, image=img)
    elif form == "interleaved":
        arrays = convert(pm.reshape(100, n, n), interleaved=np.column_stack([pos, neg]).ravel(), image=img)
    else:
        arrays = convert(pm, differential=pos - neg, image=img)
    assert "indices" in arrays and "patterns" not in arrays
    acq = recording_to_acquisition(load_recording(save_recording(tmp_path / "c.npz", **arrays)))
    order = np.argsort(acq.indices)
    assert np.array_equal(acq.indices[order], np.sort(k))
    assert np.allclose(acq.coefficients(), fwht2(img).ravel()[acq.indices])


def test_convert_column_major_mat_file_through_the_cli(tmp_path: Path) -> None:
    from scipy.io import savemat

    n = 8
    img = sphere(n)
    img[0, :] = 1.0  # break the sphere's symmetry so a transposition would show
    pm = _hadamard_rows(n, np.arange(n * n))
    cols = pm.reshape(-1, n, n).transpose(0, 2, 1).reshape(n * n, -1)  # MATLAB P(:) per pattern
    pos, neg = ((1 + pm) / 2) @ img.ravel(), ((1 - pm) / 2) @ img.ravel()
    src = tmp_path / "toolbox.mat"
    savemat(src, {"P": cols, "yp": pos, "yn": neg, "gt": img})
    out = tmp_path / "rec.npz"
    exe = Path(sys.executable).with_name("nirspi-convert")
    proc = subprocess.run(
        [
            str(exe),
            str(src),
            "-o",
            str(out),
            "--patterns",
            "P",
            "--pos",
            "yp",
            "--neg",
            "yn",
            "--image",
            "gt",
            "--flatten",
            "F",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    out_run = run_pipeline(config("source=recorded", f"source.path={out}", "camera.resolution=8"))
    assert out_run.metrics["rmse"] < 1e-9
    bad = subprocess.run(
        [str(exe), str(src), "-o", str(out), "--patterns", "P", "--pos", "nope", "--neg", "yn"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "key 'nope'" in bad.stderr


def test_differential_device() -> None:
    n = 8
    img = sphere(n)
    emu = Emulator(img, background=4.0, differential=True)
    port, thread = emu.serve_in_thread(connections=1, lifetime_s=30)
    acq = Stream(port=port, timeout_s=5).acquire(None, np.arange(n * n), n, np.random.default_rng(0))
    thread.join(timeout=10)
    assert acq.y_neg is None and acq.info["differential"]
    assert np.allclose(acq.coefficients(), fwht2(img).ravel())


@settings(max_examples=25, deadline=None)
@given(cut=st.integers(min_value=0, max_value=10_000))
def test_any_truncation_is_a_one_line_stream_error(cut: int) -> None:
    """A byte stream cut anywhere (header, frames, end marker) never yields an acquisition."""
    import io

    from nirspi_pipe.device.protocol import FRAME_DTYPE, encode_end, write_json_line
    from nirspi_pipe.sources.stream import receive_acquisition

    n, idx = 4, np.arange(16)
    buf = io.BytesIO()
    write_json_line(buf, {"protocol": "nirspi-stream/1", "n": n, "count": 16, "frame_bytes": 36, "gain": 1.0})
    frames = np.zeros(16, dtype=FRAME_DTYPE)
    frames["seq"], frames["index"], frames["t_s"] = np.arange(16), idx, np.arange(16.0)
    buf.write(frames.tobytes() + encode_end(16))
    data = buf.getvalue()
    cut = cut % len(data)
    with pytest.raises(StreamError) as err:
        receive_acquisition(io.BytesIO(data[:cut]), idx, n, "test")
    assert err.value.field in ("header", "frames", "end") and "\n" not in str(err.value)
    assert receive_acquisition(io.BytesIO(data), idx, n, "test").y_pos.size == 16
