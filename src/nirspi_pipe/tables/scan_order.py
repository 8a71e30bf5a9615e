"""The scan-order study (issue 11): the order effect of each error mechanism, paired.

Rows of ``scan_order.csv``: mechanism × sampling ratio × scan; mean ± std over objects × seeds of
the normalised PSNR at the camera's 8² resolution (``metrics.psnr``) and on the ×4 upscaled grid
(``metrics.upscale_psnr``), and the paired difference to *Basic* (mean, standard error, pairs)
for both. ``scan_order.md`` marks every difference to Basic beyond two standard errors, and its
"best" column names a scan only where the same screen supports it: the scan of highest mean 8²
PSNR, paired against every other scan, more than two standard errors above each
(:func:`best_scan`); else "none (within noise)", with the leaders when some scans are behind. From
``nirspi-run -m +experiment=scan_order``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables import _common as common

__all__ = ["best_scan", "build", "MECHANISMS"]

#: The mechanisms in the order the table shows them (experiments/mechanism/*.yaml).
MECHANISMS = ("none", "additive", "fog_trend", "led_droop", "flicker")
METRICS = {"psnr8_db": "metrics.psnr", "psnr32_db": "metrics.upscale_psnr"}


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build the scan-order study's table (CSV, Markdown) from a results frame into ``out_dir``."""
    out_dir = Path(out_dir)
    df = common.ok_rows(frame, ["mechanism", "scan.ratio", *METRICS.values()], "scan_order")
    rows = []
    mechs = [m for m in MECHANISMS if m in set(df["mechanism"])] + sorted(set(df["mechanism"]) - set(MECHANISMS))
    for mech in mechs:
        for ratio in sorted(df["scan.ratio"].unique(), reverse=True):
            sub = df[(df["mechanism"] == mech) & (df["scan.ratio"] == ratio)]
            for scan, g in common.scan_groups(sub):
                row: dict = {"mechanism": mech, "ratio": float(ratio), "scan": scan, "n": int(len(g))}
                for key, col in METRICS.items():
                    row.update(common.stats(g[col], key))
                    row.update(common.degenerate_count(g, col, key))
                    d, se, pairs = common.paired_vs_basic(sub, col, scan)
                    row.update({f"{key}_d_vs_basic": d, f"{key}_se_vs_basic": se, f"{key}_pairs": pairs})
                rows.append(row)
    table = pd.DataFrame(rows)
    common.write_csv(table, out_dir / "scan_order.csv")
    (out_dir / "scan_order.md").write_text(_markdown(table, frame, df))
    return table


def _paired(sub: pd.DataFrame, metric: str, a: str, b: str) -> tuple[float, float]:
    """Mean and standard error of ``metric(a) − metric(b)`` over the samples both scans have,
    paired as :func:`~nirspi_pipe.tables._common.paired_vs_basic` pairs them (NaN standard
    error with fewer than two pairs)."""
    keys = [k for k in common.PAIR_KEYS if k in sub.columns]
    if not keys:
        return np.nan, np.nan
    wide = sub[sub["scan"].isin([a, b])].pivot_table(index=keys, columns="scan", values=metric, aggfunc="mean")
    if a not in wide or b not in wide:
        return np.nan, np.nan
    d = (wide[a] - wide[b]).to_numpy(dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return np.nan, np.nan
    return float(d.mean()), (float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else np.nan)


def best_scan(sub: pd.DataFrame, metric: str) -> str:
    """The "best" cell for one mechanism and ratio (``sub``: its ok rows): the scan of highest
    mean ``metric`` when its paired difference to every other scan passes the table's screen
    (:func:`~nirspi_pipe.tables._common.signif`: more than two standard errors above 0); else
    "none (within noise)", naming the leaders (the top scan and those within its noise) when
    some scans are behind them. "none (degenerate)" when no scan has a score."""
    means = sub.groupby("scan")[metric].mean().dropna()
    means = means[[s for s in common.SCANS if s in means.index] + sorted(set(means.index) - set(common.SCANS))]
    if means.empty:
        return "none (degenerate)"
    top = str(means.idxmax())
    leaders = [top]
    for other in means.index:
        if other == top:
            continue
        d, se = _paired(sub, metric, top, str(other))
        if not (common.signif(d, se) and d > 0):
            leaders.append(str(other))
    if len(leaders) == 1:
        return common.SCAN_LABELS.get(top, top)
    if len(leaders) == len(means):
        return "none (within noise)"
    names = ", ".join(common.SCAN_LABELS.get(s, s) for s in means.index if s in leaders)
    return f"none (within noise: {names})"


def _cell(r: pd.Series, scan: str, key: str) -> str:

    k = int(r[f"{key}_degenerate"])
    if k >= r["n"]:
        return "degenerate"
    mark = f" ‡{k}" if k else ""  # k jobs left out as degenerate (the note under the table)
    if scan == "basic":
        return f"{r[f'{key}_mean']:.2f}{mark}"
    d, se = r[f"{key}_d_vs_basic"], r[f"{key}_se_vs_basic"]
    if not np.isfinite(d):
        return f"n/a{mark}"
    return (f"{d:+.2f} ± {se:.2f}{common.signif(d, se)}" if np.isfinite(se) else f"{d:+.2f}") + mark


def _markdown(table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame) -> str:
    lines = [
        "# Scan-order study: the order effect of each mechanism (device model)",
        "",
        "Normalised PSNR (dB). Basic: its mean; other scans: paired difference to Basic, mean ± standard error "
        "over objects × seeds († = more than two standard errors from 0). 8²: the camera's reconstruction; "
        "32²: after FSRCNN ×4, against the scene rendered at 32². Best (8²): the scan of highest mean, "
        "named only when it is more than two standard errors above every other scan (paired); else none, "
        "with the leaders that are within noise of each other.",
        "",
        "| mechanism | sampling | "
        + " | ".join(f"{common.SCAN_LABELS[s]} 8²" for s in common.SCANS)
        + " | "
        + " | ".join(f"{common.SCAN_LABELS[s]} 32²" for s in common.SCANS)
        + " | best (8²) |",
        "|---|---:|" + "---:|" * (2 * len(common.SCANS)) + "---|",
    ]
    for (mech, ratio), g in table.groupby(["mechanism", "ratio"], sort=False):
        g = g.set_index("scan")
        cells8 = [_cell(g.loc[s], s, "psnr8_db") if s in g.index else "" for s in common.SCANS]
        cells32 = [_cell(g.loc[s], s, "psnr32_db") if s in g.index else "" for s in common.SCANS]
        best = best_scan(df[(df["mechanism"] == mech) & (df["scan.ratio"] == ratio)], METRICS["psnr8_db"])
        lines.append(f"| {mech} | {ratio:.0%} | " + " | ".join(cells8) + " | " + " | ".join(cells32) + f" | {best} |")
    lines += ["", common.failures_note(frame, df), ""]
    note = common.degenerate_note(df, {"8²": METRICS["psnr8_db"], "32²": METRICS["psnr32_db"]})
    if note:
        lines += [note, ""]
    return "\n".join(lines)
