"""Table 3: improvement rate of the 3D reconstruction (Eq. 17) per scan method, fog, 5 and 15 kLux.

``improvement_pct = (RMSE_SFS − RMSE_fused) / RMSE_SFS × 100`` (``metrics.improvement_pct``), the
depth RMSE (Eq. 16) of the SFS depth made metric (Alg. A2) against that of the fused iToF mesh
(Algs. A3/A4 + heat filter). Rows: scan × kLux, mean ± std over objects × seeds, with the paper's
value, the difference (ours − paper, percentage points) and the paired difference to *Basic*.

Writes ``table3.csv``, ``table3.md`` and ``table3.png`` (bars: ours ± std and the paper's).
From ``nirspi-run -m +experiment=table3`` (the fog grid that also feeds Tables 5–7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables._common import (
    SCAN_LABELS,
    SCANS,
    bar_plot,
    conditions_note,
    failures_note,
    fmt,
    ok_rows,
    paired_vs_basic,
    paper_reference,
    scan_by_level_rows,
    signif,
    stats,
)

__all__ = ["build"]

METRIC = "metrics.improvement_pct"


def fogged(df: pd.DataFrame) -> pd.Series:
    """True for rows with fog (the ``fog`` choice, else a positive ``derived.beta_per_m``)."""
    if "fog" in df.columns:
        return df["fog"].fillna("none").astype(str) != "none"
    return df.get("derived.beta_per_m", pd.Series(0.0, index=df.index)).fillna(0.0) > 0


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 3 from a results frame into ``out_dir`` (see the module docstring)."""
    out_dir = Path(out_dir)
    df = ok_rows(frame, [METRIC, "illumination.klux"], "table3")
    df = df[fogged(df)]
    if df.empty:
        raise ValueError("table3 needs fogged jobs: run `nirspi-run -m +experiment=table3`")
    paper = paper_reference("table3").set_index(["scan", "klux"])["improvement_pct"]
    rows = []
    for klux in sorted(df["illumination.klux"].unique()):
        dk = df[df["illumination.klux"] == klux]
        for scan in SCANS:
            g = dk[dk["scan"] == scan]
            if g.empty:
                continue
            d, se, _ = paired_vs_basic(dk, METRIC, scan)
            p = float(paper.get((scan, float(klux)), np.nan))
            st = stats(g[METRIC], "improvement_pct")
            rows.append(
                {
                    "scan": scan,
                    "klux": float(klux),
                    "n": int(g[METRIC].notna().sum()),
                    **st,
                    "paper_improvement_pct": p,
                    "diff_pct_points": st["improvement_pct_mean"] - p,
                    "d_vs_basic": d,
                    "se_vs_basic": se,
                    "depth_rmse_sfs_mm_mean": float(g["metrics.depth_rmse_sfs_mm"].mean())
                    if "metrics.depth_rmse_sfs_mm" in g
                    else np.nan,
                    "depth_rmse_fused_mm_mean": float(g["metrics.depth_rmse_fused_mm"].mean())
                    if "metrics.depth_rmse_fused_mm" in g
                    else np.nan,
                }
            )
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "table3.csv", index=False, float_format="%.6g")
    (out_dir / "table3.md").write_text(_markdown(table, frame, df))
    levels = sorted(table["klux"].unique())
    series = {}
    for k in levels:
        t = table[table["klux"] == k].set_index("scan").reindex(list(SCANS))
        series[f"{k:g} kLux"] = (t["improvement_pct_mean"].tolist(), t["improvement_pct_std"].tolist())
    pap = {f"{k:g} kLux": [float(paper.get((s, float(k)), np.nan)) for s in SCANS] for k in levels}
    bar_plot(
        out_dir / "table3.png",
        "Table 3: improvement rate (Eq. 17), fog",
        [SCAN_LABELS[s] for s in SCANS],
        series,
        pap,
        "improvement of depth RMSE (%)",
    )
    return table


def _markdown(table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame) -> str:
    levels = sorted(table["klux"].unique())
    lines = [
        "# Table 3: improvement rate (Eq. 17) after Alg. A3, 3 µm fog",
        "",
        "Each cell: ours, mean ± std over objects × seeds (the paper's value). "
        "† marks a scan whose paired difference to Basic exceeds two standard errors.",
        "",
    ]
    lines += scan_by_level_rows(
        table,
        levels,
        lambda r: (
            f"{fmt(r['improvement_pct_mean'], r['improvement_pct_std'], 1)} % "
            f"({r['paper_improvement_pct']:.2f} %){signif(r['d_vs_basic'], r['se_vs_basic'])}"
        ),
    )
    lines += [
        "",
        "Paired difference to Basic (percentage points, mean ± standard error): "
        + "; ".join(
            f"{r.scan} {r.klux:g} kLux {r.d_vs_basic:+.1f} ± {r.se_vs_basic:.1f}"
            for r in table.itertuples()
            if r.scan != "basic" and np.isfinite(r.d_vs_basic)
        )
        + ".",
        "",
        f"Depth RMSE (Eq. 16), mean over all rows: SFS {table['depth_rmse_sfs_mm_mean'].mean():.1f} mm, "
        f"after Alg. A3 {table['depth_rmse_fused_mm_mean'].mean():.1f} mm. "
        f"Range of our improvement rates: {table['improvement_pct_min'].min():.1f} to {table['improvement_pct_max'].max():.1f} %.",
        "",
        f"Rows: {conditions_note(df)}; {failures_note(frame[fogged(frame)], df)}",
    ]
    return "\n".join(lines) + "\n"
