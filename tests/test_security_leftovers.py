"""Issue 32, "also from the same audit": a degenerate reference, Ctrl-C in a sweep, and
nirspi-collect on a sweep.json without jobs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from nirspi_pipe.metrics import DEGENERATE_FLAG, ImageMetrics, degenerate_reference
from nirspi_pipe.summary import metric_lines


@pytest.mark.parametrize(
    "reference", [np.full((8, 8), 0.3), np.zeros((8, 8)), np.full((8, 8), 1e-40), np.full((8, 8), 0.5) + 1e-9]
)
def test_a_degenerate_reference_leaves_the_normalised_scores_out(reference: np.ndarray) -> None:
    truth = np.zeros((8, 8))
    truth[2:6, 2:6] = 1.0
    estimate = np.random.default_rng(0).random((8, 8))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = ImageMetrics().score(truth, estimate, reference)
    assert degenerate_reference(reference) is not None
    assert "psnr" not in out and "ssim" not in out and out[DEGENERATE_FLAG] == 1.0
    assert {"psnr_raw", "ssim_raw", "rmse"} <= set(out) and all(np.isfinite(v) for v in out.values())
    assert any("undefined" in str(w.message) for w in caught)
    # the printout names no fitted score that is not there
    text = "\n".join(metric_lines(out))
    assert "SSIM/PSNR above" not in text and "no fitted SSIM/PSNR: the reference is uniform" in text


def test_a_reference_with_contrast_is_scored_as_before() -> None:
    reference = np.zeros((8, 8))
    reference[2:6, 2:6] = 1.0
    out = ImageMetrics().score(reference, reference, reference)
    assert degenerate_reference(reference) is None and DEGENERATE_FLAG not in out and out["psnr"] == 200.0


def test_collect_with_an_empty_job_list_keeps_the_records(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import nirspi_pipe
    from nirspi_pipe.app.results import collect

    sweep = tmp_path / "sweep"
    nirspi_pipe.run(["camera.resolution=8", "preset=null"], output_dir=sweep / "0123456789abcdef")
    (sweep / "sweep.json").write_text(json.dumps({"jobs": []}))
    frame = collect(sweep)
    assert len(frame) == 1 and "lists no jobs" in capsys.readouterr().err
    import shutil

    shutil.rmtree(sweep / "0123456789abcdef")
    assert len(collect(sweep)) == 0
    assert "had 1 rows and now gets 0" in capsys.readouterr().err


@pytest.mark.slow
def test_ctrl_c_in_a_sweep_is_one_line_and_resume_finishes(tmp_path: Path) -> None:
    from conftest import script

    env = {**os.environ, "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1"}
    args = [
        script("nirspi-run"),
        "-m",
        "seed=0,1,2,3,4,5,6,7",
        "camera.resolution=32",
        "preset=null",
        "hydra.sweep.dir=sweep",
        "hydra.launcher.n_jobs=1",
    ]
    proc = subprocess.Popen(args, cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list((tmp_path / "sweep").glob("*/record.json")):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1].startswith("nirspi-run: interrupted"), err
    assert "Traceback" not in err, err
    done = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(list((tmp_path / "sweep").glob("*/record.json"))) == 8
