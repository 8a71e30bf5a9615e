"""Issue 33: ``nirspi-bench gpu`` — its pieces that decide and report (the full run takes 1.5 min
without a GPU, so it is a benchmark, not a test): which back end the measured table gets, the
summary, and the CPU-only run of one part with the GPU parts skipped in one line."""

from __future__ import annotations

import json
import subprocess
import sys

from nirspi_pipe.benchmarks.gpu import SKIP_NO_GPU, _summary_md, table_rows


def _results() -> dict:
    return {
        "omp": {
            "rows": [
                {"size": 64, "atoms": 256, "numpy_ms": 27.0, "gpu_ms": 4.0, "gpu_max_diff": 1e-15},
                {"size": 128, "atoms": 1000, "numpy_ms": 300.0, "gpu_ms": 400.0, "gpu_max_diff": 1e-15},
                {"size": 256, "atoms": 1000, "numpy_ms": 900.0, "gpu_ms": 100.0, "gpu_max_diff": 1e-3},
            ]
        },
        "sfs": {
            "rows": [
                {"size": 256, "scheme": "godunov", "sweeps": 8, "numpy_ms": 80.0, "gpu_ms": 5.0},
                {"size": 256, "scheme": "lax_friedrichs", "sweeps": 272, "numpy_ms": 2400.0, "gpu_ms": 300.0},
                {"size": 64, "scheme": "godunov", "sweeps": 8, "numpy_ms": 3.0, "gpu_ms": 5.0},
                {"size": 64, "scheme": "second_order", "sweeps": 8, "numpy_ms": 30.0, "gpu_ms": 1.0},
            ]
        },
    }


def test_table_takes_the_faster_back_end_only_where_the_images_agree() -> None:
    rows = table_rows(_results(), "NVIDIA H200")["NVIDIA H200"]
    assert rows["omp"] == {64: "opencl", 128: "numpy"}  # 256²: faster but 1e-3 off, not recorded
    assert rows["sfs"] == {256: "opencl", 64: "numpy"}  # OpenCL only where it won for every scheme
    assert table_rows(_results(), None) == {}


def test_summary_has_one_row_per_measurement_and_the_ratios() -> None:
    text = _summary_md(_results(), ["    head line"])
    assert "| 64² | 256 | 27.0 | 4.0 | 0.148 |" in text
    assert "| 256² | lax_friedrichs | 272 | 2400.0 | 300.00 (-) | 0.125 |" in text
    assert "head line" in text


def test_a_cpu_only_part_runs_and_says_what_it_skipped(tmp_path) -> None:  # type: ignore[no-untyped-def]
    run = subprocess.run(
        [sys.executable, "-m", "nirspi_pipe.benchmarks.gpu", "--out", str(tmp_path), "--part", "sfs",
         "--sfs-sizes", "16", "--repeat", "1"],
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert SKIP_NO_GPU + "SFS on the GPU" in run.stdout
    rows = json.loads((tmp_path / "sfs.json").read_text())["rows"]
    assert [r["scheme"] for r in rows] == ["godunov", "lax_friedrichs", "second_order"]
    assert all(r["numpy_ms"] > 0 and "gpu_ms" not in r for r in rows)
