"""The one-run printout explains what a user would otherwise stumble on (issue 34): why the 64²
study scores low (the multiplex noise), that PSNR/SSIM are fitted where the RMSE is raw, and
which SFS baseline the printed Eq. (17) improvement uses."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

import nirspi_pipe
from nirspi_pipe.summary import format_summary, metric_lines


def _number_after(text: str, key: str) -> float:
    m = re.search(re.escape(key) + r"\s*([-+]?[0-9.]+)", text)
    assert m, f"{key!r} not in {text!r}"
    return float(m.group(1))


def test_multiplex_line_predicts_the_measured_pixel_snr() -> None:
    """The printed per-pixel SNR (reading SNR + 10·log10(2/M)) is what the reconstruction shows:
    the mean pixel over the spread of the object-free pixels, 64² exact inverse, within 1 dB."""
    r = nirspi_pipe.run(["preset=off"])  # preset=null on the command line
    line = next(s for s in format_summary(r.record()).splitlines() if "multiplex" in s)
    predicted = float(line.rsplit("=", 1)[1].split("dB")[0])
    snr, m = r.derived["snr_db"], 64 * 64
    assert predicted == pytest.approx(snr + 10 * math.log10(2 / m), abs=0.05)
    image, truth = r.reconstruction, r.products.truth
    background = ~truth.mask
    measured = 20 * math.log10(float(image.mean()) / float(image[background].std()))
    assert abs(predicted - measured) < 1.0, (predicted, measured)
    assert "hence the low SSIM/PSNR" in line  # the 64² study's -3 dB


def test_fitted_scores_and_raw_rmse_are_told_apart() -> None:
    metrics = {"ssim": 0.99, "psnr": 27.0, "rmse": 0.0708, "psnr_raw": 23.0, "ssim_raw": 0.953}
    lines = metric_lines(metrics)
    rmse = next(i for i, s in enumerate(lines) if s.startswith("RMSE"))
    assert "raw" in lines[rmse]
    note = lines[rmse + 1]
    assert "gain and offset" in note and "PSNR 23.00 dB" in note and "SSIM 0.953" in note
    # the raw PSNR is the RMSE's: 20·log10(1/RMSE)
    assert 20 * np.log10(1 / 0.0708) == pytest.approx(23.0, abs=0.05)


def test_printed_improvement_is_the_offset_free_baseline_and_names_the_others() -> None:
    metrics = {
        "depth_rmse_sfs_offsetfree_mm": 2.39,
        "depth_rmse_fused_mm": 2.05,
        "improvement_offsetfree_pct": 14.6,
        "depth_rmse_sfs_mm": 18.1,
        "improvement_pct": 88.7,
        "depth_rmse_sfs_fit_mm": 1.95,
        "improvement_fit_pct": -4.7,
    }
    text = "\n".join(metric_lines(metrics))
    assert _number_after(text, "depth RMSE, SFS") == 2.39
    assert _number_after(text, "improvement") == 14.6
    assert "working distance 18.1 mm (+88.7 %)" in text and "global fit 1.95 mm (-4.7 %)" in text
    assert "(+0 more" not in text and text.count("\n") == 4  # 3 explained lines, the note, nothing else


def test_error_messages_show_plain_numbers() -> None:
    """A numpy scalar in a ConfigError reads as the number (issue 34: ``np.float64(0.0)``)."""
    from nirspi_pipe.errors import ConfigError

    msg = str(ConfigError("scene.distance_mm", np.float64(0.0), "a distance in mm > 0"))
    assert msg == "scene.distance_mm=0.0 is not allowed; allowed: a distance in mm > 0"
    assert "np." not in str(ConfigError("k", np.int64(3), "x")) and "'a'" in str(ConfigError("k", "a", "x"))
    assert "array" in str(ConfigError("k", np.zeros(2), "x"))  # an array stays an array


def test_collect_prints_its_own_name(tmp_path, monkeypatch, capsys) -> None:
    """Tables built by nirspi-collect are announced as nirspi-collect's (issue 34)."""
    import sys

    import pandas as pd

    from nirspi_pipe.app import results

    monkeypatch.setattr(results, "build_table", lambda *a, **k: None)
    for prog, expected in (
        ("/usr/bin/nirspi-collect", "nirspi-collect: table t ->"),
        ("nirspi-run", "nirspi-run: table t ->"),
    ):
        monkeypatch.setattr(sys, "argv", [prog])
        assert results.build_tables(pd.DataFrame(), tmp_path, ["t"]) == ["t"]
        assert capsys.readouterr().out.startswith(expected)


def test_reproduction_check_shows_plain_values() -> None:
    """A cell that differs in a column of mixed types is shown as its value, not as numpy's repr."""
    import pandas as pd

    from nirspi_pipe.reproduce import compare_tables

    new = pd.DataFrame({"scan": ["basic", "spiral"], "v": [np.float64(0.0), "x"]})
    ref = pd.DataFrame({"scan": ["basic", "spiral"], "v": [np.float64(0.5), "x"]})
    problems = compare_tables(new, ref, rtol=0.0, atol=0.0)
    assert problems == ["row 0 column v: 0.0 vs reference 0.5"], problems
