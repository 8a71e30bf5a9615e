"""Table 3: improvement rate of the 3D reconstruction (Eq. 17) per scan method, fog, 5 and 15 kLux.

``(RMSE_SFS − RMSE_fused) / RMSE_SFS × 100``, the depth RMSE (Eq. 16) of the SFS depth made
metric (Alg. A2) against that of the fused iToF mesh (Algs. A3/A4 + heat filter), with three
baselines (:mod:`nirspi_pipe.mesh.metrics3d`): **offset-free** (primary: the geometric scale with
the best constant offset, ``metrics.improvement_offsetfree_pct``), **centre-placed** (the SFS
median placed at the set-up's 20 cm, ``metrics.improvement_pct``; the ``improvement_pct_*``
columns, kept for the CI reference) and **global-fit** (``metrics.improvement_fit_pct``). Rows:
scan × kLux, mean ± std over objects × seeds, the standard error clustered by seed
(:mod:`nirspi_pipe.stats`), the paper's value, the difference (ours − paper, percentage points)
and the paired difference to *Basic*.

Writes ``table3.csv``, ``table3.md``, ``table3.png`` (bars: ours ± SE and the paper's),
``table3_rankings.csv`` (every pairwise comparison per kLux and baseline, Holm, both seed halves)
and ``table3_objects.csv`` (per object and kLux: the three baselines and the offset's share).
From ``nirspi-run -m +experiment=table3`` (the fog grid that also feeds Tables 5–7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.stats import across_families
from nirspi_pipe.tables import _common as common

__all__ = ["build"]

METRIC = "metrics.improvement_pct"
#: The three baselines of Eq. 17: key -> record column (the first is the primary one).
BASELINES = {
    "offsetfree": "metrics.improvement_offsetfree_pct",
    "centre": "metrics.improvement_pct",
    "fit": "metrics.improvement_fit_pct",
}
#: Each baseline's depth RMSE column (Eq. 16), for Eq. 17 of a cell's mean RMSEs.
BASELINE_RMSE = {
    "offsetfree": "metrics.depth_rmse_sfs_offsetfree_mm",
    "centre": "metrics.depth_rmse_sfs_mm",
    "fit": "metrics.depth_rmse_sfs_fit_mm",
}
FUSED_RMSE = "metrics.depth_rmse_fused_mm"
#: The fusion's own flag: its fit says the fused depth is expected to be worse than SFS alone
#: (:func:`nirspi_pipe.mesh.anchors.worse_than_prior`); flagged jobs stay in the means and are counted.
FLAG = "info.fusion.worse_than_sfs"


def flagged(g: pd.DataFrame) -> float:
    """How many rows of ``g`` the fusion flagged worse than SFS alone; NaN when the records
    carry no flag (made before the flag existed)."""
    if FLAG not in g:
        return np.nan
    return float(g[FLAG].map(lambda v: v is True or v == 1 or str(v).lower() == "true").sum())


def fogged(df: pd.DataFrame) -> pd.Series:
    """True for rows with fog (the ``fog`` choice, else a positive ``derived.beta_per_m``)."""
    if "fog" in df.columns:
        return df["fog"].fillna("none").astype(str) != "none"
    return df.get("derived.beta_per_m", pd.Series(0.0, index=df.index)).fillna(0.0) > 0


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 3 from a results frame into ``out_dir`` (see the module docstring)."""
    out_dir = Path(out_dir)
    df = common.ok_rows(frame, [METRIC, "illumination.klux"], "table3")
    df = df[fogged(df)]
    if df.empty:
        raise ValueError("table3 needs fogged jobs: run `nirspi-run -m +experiment=table3`")
    paper = common.paper_reference("table3").set_index(["scan", "klux"])["improvement_pct"]
    rows = []
    for klux, dk in common.klux_levels(df):
        for scan, g in common.scan_groups(dk):
            d, se, _ = common.paired_vs_basic(dk, METRIC, scan)
            p = float(paper.get((scan, float(klux)), np.nan))
            st = common.stats(g[METRIC], "improvement_pct")
            rows.append(
                {
                    "scan": scan,
                    "klux": float(klux),
                    "n": int(g[METRIC].notna().sum()),
                    "flagged": flagged(g),
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
                    **_baselines(g),
                }
            )
    table = pd.DataFrame(rows)
    claims = across_families(_rankings(df))
    common.write_csv(claims, out_dir / "table3_rankings.csv")
    objects = _objects(df)
    common.write_csv(objects, out_dir / "table3_objects.csv")
    common.write_csv(table, out_dir / "table3.csv")
    (out_dir / "table3.md").write_text(common.with_families(_markdown(table, frame, df, claims, objects), claims))
    levels = sorted(table["klux"].unique())
    series = {}
    prim = "offsetfree" if "offsetfree_mean" in table else "centre"
    for k in levels:
        t = table[table["klux"] == k].set_index("scan").reindex(list(common.SCANS))
        series[f"{k:g} kLux"] = (t[f"{prim}_mean"].tolist(), t[f"{prim}_se"].fillna(0).tolist())
    pap = {f"{k:g} kLux": [float(paper.get((s, float(k)), np.nan)) for s in common.SCANS] for k in levels}
    bar = common.bar_figure(
        "Table 3: improvement rate (Eq. 17), fog",
        [common.SCAN_LABELS[s] for s in common.SCANS],
        series,
        pap,
        "improvement of depth RMSE (%), " + ("offset-free baseline" if prim == "offsetfree" else "centre-placed"),
        "Error bars: ± 1 standard error of the cell's mean, clustered by seed (objects and scans of one seed "
        "share its noise draws); hatched: the paper's Table 3.",
    )
    common.save_figure(out_dir / "table3.png", bar)
    return table


def _baselines(g: pd.DataFrame) -> dict[str, float]:
    """Mean, clustered SE and number of seeds of each baseline's improvement over one cell."""
    out: dict[str, float] = {}
    for key, col in BASELINES.items():
        if col not in g:
            continue
        out[f"{key}_mean"] = float(g[col].mean())
        out.update(common.cell(g, col, key))
        rm = BASELINE_RMSE[key]
        if rm in g and FUSED_RMSE in g:  # Eq. 17 of the mean RMSEs (not the mean of the jobs' rates)
            before, after = float(g[rm].mean()), float(g[FUSED_RMSE].mean())
            out[f"{key}_of_means"] = (before - after) / before * 100 if before > 0 else np.nan
    return out


def _rankings(df: pd.DataFrame) -> pd.DataFrame:
    parts = []
    for klux, dk in common.klux_levels(df):
        for key, col in BASELINES.items():
            if col in dk and dk[col].notna().any():
                parts.append(
                    common.ranking(dk, col, higher_is_better=True, where={"klux": float(klux), "baseline": key})
                )
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def _objects(df: pd.DataFrame) -> pd.DataFrame:
    """Per object and kLux (scans × seeds pooled): the three baselines' improvement, the
    centre-placed baseline's offset (mean, mm) and its share of that baseline's squared error
    (``mean(offset²) / mean(RMSE_centre²)``)."""
    rows = []
    if "scene" not in df:
        return pd.DataFrame()
    for (scene, klux), g in df.groupby(["scene", "illumination.klux"], sort=False):
        row: dict = {"scene": scene, "klux": float(klux), "n": int(len(g))}
        row.update(_baselines(g))
        if "metrics.sfs_offset_mm" in g and "metrics.depth_rmse_sfs_mm" in g:
            off, r = g["metrics.sfs_offset_mm"], g["metrics.depth_rmse_sfs_mm"]
            row["offset_mm_mean"] = float(off.mean())
            row["offset_share"] = float((off**2).mean() / (r**2).mean())
            row["depth_rmse_centre_mm_mean"] = float(r.mean())
            row["depth_rmse_offsetfree_mm_mean"] = float(g["metrics.depth_rmse_sfs_offsetfree_mm"].mean())
        rows.append(row)
    order = {s: i for i, s in enumerate(("sphere", "torus", "cube", "u_shape"))}
    out = pd.DataFrame(rows)
    return out.sort_values(["scene", "klux"], key=lambda c: c.map(order) if c.name == "scene" else c).reset_index(
        drop=True
    )


def _markdown(
    table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame, claims: pd.DataFrame, objects: pd.DataFrame
) -> str:
    has_free = "offsetfree_mean" in table
    lines = [
        "# Table 3: improvement rate (Eq. 17) after Alg. A3, 3 µm fog",
        "",
        "Each cell: ours, mean ± standard error clustered by seed (n jobs = objects × seeds), for the "
        "offset-free baseline (primary), the centre-placed and the global-fit baselines; the paper's value.",
        "",
        "| scan | kLux | paper | offset-free (primary) | centre-placed | global-fit | n | flagged |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in table.itertuples():
        cells = [
            common.fmt(getattr(r, f"{k}_mean", np.nan), getattr(r, f"{k}_se", np.nan), 1)
            for k in (("offsetfree", "centre", "fit") if has_free else ("centre", "fit"))
        ]
        if not has_free:
            cells.insert(0, "n/a")
        lines.append(
            f"| {common.SCAN_LABELS[r.scan]} | {r.klux:g} | {r.paper_improvement_pct:.2f} | "
            + " | ".join(cells)
            + f" | {r.n} | {'n/a' if np.isnan(r.flagged) else int(r.flagged)} |"
        )
    total = flagged(df)
    lines += [
        "",
        "Flagged: "
        + (
            "n/a (the records carry no `info.fusion.worse_than_sfs`)."
            if np.isnan(total)
            else f"{int(total)} of {len(df)} jobs carry `info.fusion.worse_than_sfs` (the fusion's own fit, "
            "without the ground truth, expects its depth to be worse than SFS placed at the working distance: "
            "its anchors scatter beyond their stated noise); they are kept in every mean above."
        ),
    ]
    if has_free and "offsetfree_of_means" in table:
        lines += [
            "",
            "Eq. 17 of each cell's mean RMSEs (instead of the mean of the jobs' rates), offset-free / "
            "centre-placed / global-fit: "
            + "; ".join(
                f"{common.SCAN_LABELS[r.scan]} {r.klux:g} kLux {r.offsetfree_of_means:.1f} / {r.centre_of_means:.1f} / "
                f"{r.fit_of_means:.1f} %"
                for r in table.itertuples()
            )
            + ".",
        ]
    lines += ["", _claims_lines(claims), ""]
    if len(objects) and "offset_share" in objects:
        lines += [
            "Per object (scans × seeds pooled): improvement with the offset-free / centre-placed / "
            "global-fit baseline (mean ± SE), the centre-placed baseline's offset (true − baseline, mean) "
            "and its share of that baseline's squared error:",
            "",
            "| object | kLux | offset-free | centre-placed | global-fit | offset (mm) | offset's share | n |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for o in objects.itertuples():
            lines.append(
                f"| {o.scene} | {o.klux:g} | {common.fmt(o.offsetfree_mean, o.offsetfree_se, 1)} | "
                f"{common.fmt(o.centre_mean, o.centre_se, 1)} | {common.fmt(o.fit_mean, o.fit_se, 1)} | "
                f"{o.offset_mm_mean:+.1f} | {100 * o.offset_share:.0f} % | {o.n} |"
            )
        lines.append("")
    lines += [
        f"Depth RMSE (Eq. 16), mean over all rows: SFS centre-placed {table['depth_rmse_sfs_mm_mean'].mean():.1f} mm, "
        f"after Alg. A3 {table['depth_rmse_fused_mm_mean'].mean():.1f} mm.",
        "",
        common.rows_note(df, frame[fogged(frame)]),
    ]
    return "\n".join(lines) + "\n"


def _claims_lines(claims: pd.DataFrame) -> str:
    """One line per kLux and baseline: the replicated claims."""
    if claims.empty:
        return "Rankings: no comparison possible."
    parts = []
    for (klux, base), c in claims.groupby(["klux", "baseline"], sort=False):
        parts.append(f"{klux:g} kLux, {base}: {common.ranking_note(c)}")
    return (
        "Rankings (a scan better than another only where the paired difference holds after Holm's correction "
        "over the six pairs in both seed halves): " + "; ".join(parts) + "."
    )
