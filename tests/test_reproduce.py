"""The reproduction checker: tolerances, timing columns excluded, clear differences."""

from __future__ import annotations

import numpy as np
import pandas as pd

from nirspi_pipe.reproduce import compare_tables, is_timing_column


def test_timing_columns_are_excluded() -> None:
    ref = pd.DataFrame({"scan": ["basic", "spiral"], "psnr": [20.0, 25.0], "time_ms": [1.0, 2.0]})
    new = ref.assign(time_ms=[50.0, 70.0])
    assert compare_tables(new, ref, rtol=1e-6, atol=0) == []
    assert is_timing_column("timings_ms.solver") and not is_timing_column("metrics.psnr")


def test_numeric_tolerance_and_text_differences_are_reported() -> None:
    ref = pd.DataFrame({"scan": ["basic", "spiral"], "psnr": [20.0, np.nan]})
    assert compare_tables(ref.assign(psnr=[20.0 + 1e-9, np.nan]), ref, rtol=1e-6, atol=0) == []
    problems = compare_tables(ref.assign(psnr=[21.0, np.nan]), ref, rtol=1e-3, atol=0)
    assert len(problems) == 1 and "psnr" in problems[0] and "21" in problems[0]
    problems = compare_tables(ref.assign(scan=["basic", "hilbert"]), ref, rtol=1e-3, atol=0)
    assert len(problems) == 1 and "hilbert" in problems[0]
    assert compare_tables(ref.iloc[:1], ref, 1e-3, 0)  # row count differs
    assert compare_tables(ref.drop(columns="psnr"), ref, 1e-3, 0)  # column missing


def test_all_nan_columns_compare_equal() -> None:
    ref = pd.DataFrame({"scan": ["basic"], "skew": [np.nan]})
    assert compare_tables(ref.copy(), ref, rtol=1e-6, atol=0) == []
