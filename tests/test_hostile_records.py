"""No NaN or Inf in a record with status ok (docs/hostile.md): the guard, and the runs the issue
found (``camera.resolution=2``)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.app.jobs import execute_job
from nirspi_pipe.finite import drop_nonfinite, is_finite_tree

leaf = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(),
    st.text(max_size=5),
    st.booleans(),
    st.none(),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=3),
)
tree = st.recursive(
    leaf, lambda inner: st.dictionaries(st.text(min_size=1, max_size=6), inner, max_size=4), max_leaves=8
)


def count_bad(node: object) -> int:
    if isinstance(node, dict):
        return sum(count_bad(v) for v in node.values())
    return 0 if is_finite_tree(node) else 1


@settings(max_examples=40, deadline=None)
@given(
    sections=st.fixed_dictionaries(
        {
            k: st.dictionaries(st.text(min_size=1, max_size=6), tree, max_size=3)
            for k in ("metrics", "derived", "info", "timings_ms")
        }
    )
)
def test_guard_leaves_only_finite_values_and_says_what_it_removed(sections: dict) -> None:
    record = {"config": {"x": float("nan")}, **copy.deepcopy(sections)}
    expected = sum(count_bad(v) for v in sections.values())
    warnings = drop_nonfinite(record)
    assert len(warnings) == expected
    assert all(is_finite_tree(record[k]) for k in sections)
    assert math.isnan(record["config"]["x"])  # the user's input is not a result: untouched
    json.dumps({k: record[k] for k in sections}, allow_nan=False)  # strict JSON now
    for w in warnings:
        assert "left out of the record" in w and "\n" not in w


def test_resolution_2_records_no_nan_and_says_why(tmp_path: Path) -> None:
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["camera.resolution=2"])
    rec = execute_job(cfg, tmp_path, {}, [])
    assert rec["meta"]["status"] == "ok"
    # 2x2 pixels of the centred sphere see the same radiance: a degenerate (uniform) reference, so
    # the normalised scores are left out too (issue 32), and the raw SSIM is undefined below 3x3
    assert "ssim" not in rec["metrics"] and "ssim_raw" not in rec["metrics"] and math.isfinite(rec["metrics"]["rmse"])
    assert rec["metrics"]["degenerate_reference"] == 1.0
    assert any(
        "metrics.ssim_raw=nan" in w and "SSIM is undefined for images smaller than 3x3" in w
        for w in rec["meta"]["warnings"]
    )
    stored = json.loads((tmp_path / "record.json").read_text())
    assert all(is_finite_tree(stored[k]) for k in ("metrics", "derived", "info", "timings_ms"))


# ------------------------------------------------------------------ issue 41: regular files only, bounded


def _hostile_sweep(root: Path) -> Path:
    """A sweep folder whose job folders hold a FIFO, a list, a string ``meta``, JSON nested
    100 000 deep as ``record.json``, and a job folder that is a link to a file."""
    import os

    sweep = root / "sweep"
    for name in "abcd":
        (sweep / name).mkdir(parents=True)
    os.mkfifo(sweep / "a" / "record.json")
    (sweep / "b" / "record.json").write_text("[1, 2]")
    (sweep / "c" / "record.json").write_text('{"meta": "x"}')
    (sweep / "d" / "record.json").write_text("[" * 100_000 + "]" * 100_000)
    (root / "file").write_text("x")
    (sweep / "e").symlink_to(root / "file")
    return sweep


def test_read_record_refuses_what_is_not_a_regular_record(tmp_path: Path) -> None:
    import pytest

    from nirspi_pipe.records import read_record

    sweep = _hostile_sweep(tmp_path)
    for path, what in [
        (sweep / "a" / "record.json", "a FIFO"),
        (Path("/dev/zero"), "a device"),
        (sweep / "b", "a folder"),
        (sweep / "b" / "record.json", "list, not a record"),
        (sweep / "c" / "record.json", "meta is not an object"),
        (sweep / "d" / "record.json", "nested too deep"),
        (sweep / "e" / "record.json", "cannot open"),
    ]:
        with pytest.raises(ValueError, match=what):
            read_record(path)


def test_collect_and_load_results_never_hang_on_hostile_records(tmp_path: Path) -> None:
    """``nirspi-collect`` and ``load_results`` on the folder above: a failed row per record
    that is not one, one warning line each, exit 0, no traceback (in a child, bounded)."""
    import subprocess
    import sys

    from conftest import script

    sweep = _hostile_sweep(tmp_path)
    res = subprocess.run([script("nirspi-collect"), str(sweep)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "4 records (4 failed)" in res.stdout and res.stderr.count("unreadable record") == 4, res.stdout
    code = f"import nirspi_pipe; print(sorted(nirspi_pipe.load_results({str(sweep)!r}, refresh=True)['status']))"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "['failed', 'failed', 'failed', 'failed']", res.stderr[-2000:]


def test_nirspi_convert_refuses_fifos_and_devices(tmp_path: Path) -> None:
    import os
    import subprocess

    from conftest import script

    for name in ("in.npz", "in.mat"):
        os.mkfifo(tmp_path / name)
    for src in (tmp_path / "in.npz", tmp_path / "in.mat", Path("/dev/zero")):
        res = subprocess.run(
            [
                script("nirspi-convert"),
                str(src),
                "-o",
                str(tmp_path / "o.npz"),
                "--patterns",
                "P",
                "--measurements",
                "y",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert res.returncode == 2 and "not a regular file" in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1


def test_collect_keeps_no_nan_in_ok_rows_and_prints_no_control_characters(tmp_path: Path) -> None:
    """A record written by someone else with status ``ok`` and NaN/Inf metrics: the values are
    left out of the row with a warning naming them; text with ANSI escapes, CR and a bidi
    override reaches the terminal (``--print-table``) replaced."""
    import subprocess

    import pandas as pd

    from conftest import script

    sweep = tmp_path / "sweep"
    for job in ("j1", "j2"):
        (sweep / job).mkdir(parents=True)
    (sweep / "j1" / "record.json").write_text(
        '{"meta": {"status": "ok"}, "metrics": {"psnr": NaN, "ssim": Infinity, "mse": 0.5}}'
    )
    (sweep / "j2" / "record.json").write_text(
        json.dumps({"meta": {"status": "failed", "error": "\x1b[2J\rgone\u202eevil"}})
    )
    res = subprocess.run(
        [script("nirspi-collect"), "--print-table", str(sweep)], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert "metrics.psnr=nan left out" in res.stderr and "metrics.ssim=inf left out" in res.stderr
    assert not any(c in res.stdout + res.stderr for c in ("\x1b", "\r", "\u202e")), res.stdout
    frame = pd.read_parquet(sweep / "results.parquet")
    ok = frame[frame["status"] == "ok"]
    assert "metrics.psnr" not in frame.columns or ok["metrics.psnr"].isna().all()
    assert ok["metrics.mse"].tolist() == [0.5]
    numeric = ok.select_dtypes("number").to_numpy(dtype=float)
    assert not (~pd.isna(numeric) & ~(abs(numeric) < float("inf"))).any()


def test_the_input_hash_covers_regular_files_only(tmp_path: Path) -> None:
    """``meta.inputs`` (docs/hostile.md): string leaves naming existing regular files, relative
    to the working directory, the ``hydra`` node aside; a FIFO, a device, a folder are not inputs
    (and are never opened to be hashed)."""
    import os

    from nirspi_pipe.jobkey import InputHasher

    (tmp_path / "rec.npz").write_bytes(b"data")
    os.mkfifo(tmp_path / "fifo")
    config = {
        "source": {"path": "rec.npz"},
        "scene": {"path": str(tmp_path / "fifo"), "other": "/dev/zero", "dir": str(tmp_path)},
        "hydra": {"run": {"dir": "rec.npz"}},
    }
    hashes = InputHasher().hashes(config, base=tmp_path)
    assert set(hashes) == {"source.path"} and len(hashes["source.path"]) == 64
