"""Table 6: processing time of the 3D reconstruction per scan method.

* ``time_sfs_ms``: ``timings_ms.sfs``, the SFS stage (Alg. A2; its back end is in ``sfs_backend``);
* ``time_3dmesh_ms``: ``timings_ms.fusion + timings_ms.surface``, the 3D mesh stage(s): iToF
  mapping (Algs. A3/A4, voxel merging, outlier removal, heat filter) plus the power crust. The
  iToF *measurement* (``timings_ms.itof``) simulates the device and is not processing, so it is
  left out, as are the 2D stages;
* ``time_total_ms``: their sum per job (the paper's Time_Total = Time_SFS + Time_3Dmesh).

Mean ± std over the fog grid's jobs (objects × seeds × kLux), the paper's numbers and our/paper
ratios. Timings depend on the machine and its load: they are excluded from reproduction checks
(:mod:`nirspi_pipe.reproduce`). Writes ``table6.csv``, ``table6.md``, ``table6.png``.
From ``nirspi-run -m +experiment=table6`` (the fog grid of Table 3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables import _common as common
from nirspi_pipe.tables.table3 import fogged

__all__ = ["build", "stage_times"]

KEYS = ("time_sfs_ms", "time_3dmesh_ms", "time_total_ms")


def stage_times(df: pd.DataFrame) -> pd.DataFrame:
    """Per-job ``time_sfs_ms``, ``time_3dmesh_ms`` (fusion + surface) and ``time_total_ms``."""
    sfs = df["timings_ms.sfs"].astype(float)
    mesh = df["timings_ms.fusion"].astype(float) + df["timings_ms.surface"].astype(float)
    return pd.DataFrame({"time_sfs_ms": sfs, "time_3dmesh_ms": mesh, "time_total_ms": sfs + mesh}, index=df.index)


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 6 from a results frame into ``out_dir`` (see the module docstring)."""
    out_dir = Path(out_dir)
    df = common.ok_rows(frame, ["timings_ms.sfs", "timings_ms.fusion", "timings_ms.surface"], "table6")
    if fogged(df).any():  # the paper's timing runs are the fog runs of Tables 3/5/7
        df = df[fogged(df)]
    times = stage_times(df)
    paper = common.paper_reference("table6").set_index("scan")
    backend = "info.sfs.backend"
    rows = []
    for scan, g in common.scan_groups(df):
        row: dict = {"scan": scan, "n": int(len(g))}
        if backend in df.columns:
            row["sfs_backend"] = ",".join(sorted(g[backend].dropna().astype(str).unique()))
        for key in KEYS:
            row.update(common.stats(times.loc[g.index, key], key))
        for key in KEYS:
            p = float(paper.loc[scan, key]) if scan in paper.index else np.nan
            row[f"paper_{key}"] = p
            row[f"{key}_ratio"] = row[f"{key}_mean"] / p if p else np.nan
        rows.append(row)
    table = pd.DataFrame(rows)
    common.write_csv(table, out_dir / "table6.csv")
    (out_dir / "table6.md").write_text(_markdown(table, frame, df))
    t = table.set_index("scan").reindex(list(common.SCANS))
    bar = common.bar_figure(
        "Table 6: 3D processing time per job",
        [common.SCAN_LABELS[s] for s in common.SCANS],
        {
            "SFS": (t["time_sfs_ms_mean"].tolist(), t["time_sfs_ms_std"].tolist()),
            "3D mesh": (t["time_3dmesh_ms_mean"].tolist(), t["time_3dmesh_ms_std"].tolist()),
        },
        {"SFS": t["paper_time_sfs_ms"].tolist(), "3D mesh": t["paper_time_3dmesh_ms"].tolist()},
        "ms",
        f"Error bars: ± 1 standard deviation of the jobs' times ({common.count_range(t['n'])} jobs "
        "per scan: objects × kLux × seeds), the spread between jobs, not the uncertainty of the mean.",
    )
    common.save_figure(out_dir / "table6.png", bar)
    return table


def _markdown(table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame) -> str:
    backends = sorted(
        {b for v in table.get("sfs_backend", pd.Series(dtype=str)).dropna() for b in str(v).split(",") if b}
    )
    lines = [
        "# Table 6: 3D reconstruction processing time (ms)",
        "",
        "Each cell: ours, mean ± std over jobs (the paper's value). Time_3Dmesh = iToF mapping "
        "(Algs. A3/A4 + heat filter) + power crust; Time_Total = Time_SFS + Time_3Dmesh. "
        f"SFS back end: {', '.join(backends) or 'unknown'}. Timings depend on the machine and its load "
        "(sweep jobs run in parallel) and are not part of the reproduction check.",
        "",
        "| Scanning method | Time SFS (ms) | Time 3D mesh (ms) | Time total (ms) |",
        "|---|---:|---:|---:|",
    ]
    for r in table.itertuples():
        cells = [
            f"{common.fmt(getattr(r, f'{k}_mean'), getattr(r, f'{k}_std'), 1)} ({getattr(r, f'paper_{k}'):.2f})"
            for k in KEYS
        ]
        lines.append(f"| {common.SCAN_LABELS[r.scan]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Ours / paper (total): "
        + ", ".join(f"{common.SCAN_LABELS[r.scan]} {r.time_total_ms_ratio:.2f}×" for r in table.itertuples())
        + ".",
        "",
        common.rows_note(df, frame[fogged(frame)] if fogged(df).all() else frame),
    ]
    return "\n".join(lines) + "\n"
