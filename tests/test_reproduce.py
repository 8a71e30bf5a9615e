"""The reproduction checker: tolerances, timing columns excluded, clear differences."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from nirspi_pipe.reproduce import (
    _tolerances,
    check,
    compare_tables,
    is_timing_column,
    reference_dir,
)


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


# -- the check catches a real change (issue 12) --------------------------------------------------


def _fake_sweep(tmp_path: Path) -> tuple[Path, Path]:
    """A sweep whose tables are the committed references, and a copy of the reference folder."""
    ref = tmp_path / "ref"
    shutil.copytree(reference_dir(), ref)
    tables = tmp_path / "sweep" / "tables"
    tables.mkdir(parents=True)
    for csv in ref.glob("*.csv"):
        shutil.copyfile(csv, tables / csv.name)
    return tmp_path / "sweep", ref


def test_every_compared_cell_catches_a_one_percent_change(tmp_path: Path) -> None:
    """The tolerances are tight enough that moving any compared, non-zero number of any reference
    table by 1 % fails the check (and the unmodified tables pass)."""
    sweep, ref = _fake_sweep(tmp_path)
    assert all(not problems for problems in check(sweep, ref).values())
    moved = 0
    for csv in sorted(ref.glob("*.csv")):
        frame = pd.read_csv(csv)
        rtol, atol = _tolerances(ref, csv.stem)  # read once per table, not once per cell
        for col in frame.columns:
            if is_timing_column(col) or not pd.api.types.is_numeric_dtype(frame[col]):
                continue
            new = frame.astype({col: float})  # one cell moved at a time, then put back
            for i in np.flatnonzero(np.isfinite(frame[col].to_numpy(float)) & (frame[col] != 0).to_numpy()):
                new.loc[i, col] = float(frame.loc[i, col]) * 1.01
                problems = compare_tables(new, frame, rtol, atol)
                assert len(problems) == 1 and col in problems[0], (csv.name, col, i, problems)
                new.loc[i, col] = float(frame.loc[i, col])
                moved += 1
    assert moved > 100  # the check above ran over the real tables


@pytest.mark.slow
def test_a_one_percent_change_of_plancks_constant_fails_the_table3_check(monkeypatch: pytest.MonkeyPatch) -> None:
    """One CI job of Table 3 (basic scan, 5 kLux, sphere, seed 0), run as shipped and with the
    Planck constant of the photon budget 1 % larger (1 % fewer signal photons per watt): the
    Table 3 cells it feeds (depth RMSE of SFS and fused depth, improvement, Eq. 16/17) move by
    more than Table 3's stated tolerance, so the CI check would fail."""
    from hydra import compose, initialize_config_module

    from nirspi_pipe.physics import budget
    from nirspi_pipe.pipeline import run_pipeline

    overrides = ["+experiment=table3_ci", "scan=basic", "illumination.klux=5", "scene=sphere", "seed=0"]
    with initialize_config_module(config_module="nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides)
    cols = ["depth_rmse_sfs_mm", "depth_rmse_fused_mm", "improvement_pct"]
    nominal = pd.DataFrame([{c: run_pipeline(cfg).metrics[c] for c in cols}])
    monkeypatch.setattr(budget, "H_PLANCK", budget.H_PLANCK * 1.01)
    changed = pd.DataFrame([{c: run_pipeline(cfg).metrics[c] for c in cols}])
    rtol, atol = _tolerances(reference_dir(), "table3")
    problems = compare_tables(changed, nominal, rtol, atol)
    assert problems, (nominal, changed, rtol)
