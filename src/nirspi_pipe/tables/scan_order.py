"""The scan-order study (issue 11): the order effect of each error mechanism, paired.

Rows of ``scan_order.csv``: mechanism × sampling ratio × scan; mean ± std over objects × seeds of
the normalised PSNR at the camera's 8² resolution (``metrics.psnr``) and on the ×4 upscaled grid
(``metrics.upscale_psnr``), and the paired difference to *Basic* (mean, standard error, pairs)
for both. ``scan_order.md`` states for every mechanism and ratio whether any scan differs from
Basic by more than two standard errors, and which scan is best. From
``nirspi-run -m +experiment=scan_order``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables._common import (
    SCAN_LABELS,
    SCANS,
    degenerate_count,
    degenerate_note,
    failures_note,
    ok_rows,
    paired_vs_basic,
    signif,
    stats,
)

__all__ = ["build", "MECHANISMS"]

#: The mechanisms in the order the table shows them (experiments/mechanism/*.yaml).
MECHANISMS = ("none", "additive", "fog_trend", "led_droop", "flicker")
METRICS = {"psnr8_db": "metrics.psnr", "psnr32_db": "metrics.upscale_psnr"}


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build the scan-order study's table (CSV, Markdown) from a results frame into ``out_dir``."""
    out_dir = Path(out_dir)
    df = ok_rows(frame, ["mechanism", "scan.ratio", *METRICS.values()], "scan_order")
    rows = []
    mechs = [m for m in MECHANISMS if m in set(df["mechanism"])] + sorted(set(df["mechanism"]) - set(MECHANISMS))
    for mech in mechs:
        for ratio in sorted(df["scan.ratio"].unique(), reverse=True):
            sub = df[(df["mechanism"] == mech) & (df["scan.ratio"] == ratio)]
            for scan in SCANS:
                g = sub[sub["scan"] == scan]
                if g.empty:
                    continue
                row: dict = {"mechanism": mech, "ratio": float(ratio), "scan": scan, "n": int(len(g))}
                for key, col in METRICS.items():
                    row.update(stats(g[col], key))
                    row.update(degenerate_count(g, col, key))
                    d, se, pairs = paired_vs_basic(sub, col, scan)
                    row.update({f"{key}_d_vs_basic": d, f"{key}_se_vs_basic": se, f"{key}_pairs": pairs})
                rows.append(row)
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "scan_order.csv", index=False, float_format="%.6g")
    (out_dir / "scan_order.md").write_text(_markdown(table, frame, df))
    return table


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
    return (f"{d:+.2f} ± {se:.2f}{signif(d, se)}" if np.isfinite(se) else f"{d:+.2f}") + mark


def _markdown(table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame) -> str:
    lines = [
        "# Scan-order study: the order effect of each mechanism (device model)",
        "",
        "Normalised PSNR (dB). Basic: its mean; other scans: paired difference to Basic, mean ± standard error "
        "over objects × seeds († = more than two standard errors from 0). 8²: the camera's reconstruction; "
        "32²: after FSRCNN ×4, against the scene rendered at 32².",
        "",
        "| mechanism | sampling | "
        + " | ".join(f"{SCAN_LABELS[s]} 8²" for s in SCANS)
        + " | "
        + " | ".join(f"{SCAN_LABELS[s]} 32²" for s in SCANS)
        + " | best (8²) |",
        "|---|---:|" + "---:|" * (2 * len(SCANS)) + "---|",
    ]
    for (mech, ratio), g in table.groupby(["mechanism", "ratio"], sort=False):
        g = g.set_index("scan")
        cells8 = [_cell(g.loc[s], s, "psnr8_db") if s in g.index else "" for s in SCANS]
        cells32 = [_cell(g.loc[s], s, "psnr32_db") if s in g.index else "" for s in SCANS]
        best = g["psnr8_db_mean"].idxmax() if g["psnr8_db_mean"].notna().any() else "none (degenerate)"
        sig = any(
            abs(g.loc[s, "psnr8_db_d_vs_basic"]) > 2 * g.loc[s, "psnr8_db_se_vs_basic"]
            for s in g.index
            if s != "basic" and np.isfinite(g.loc[s, "psnr8_db_se_vs_basic"])
        )
        lines.append(
            f"| {mech} | {ratio:.0%} | "
            + " | ".join(cells8)
            + " | "
            + " | ".join(cells32)
            + f" | {SCAN_LABELS.get(best, best)}{'' if sig else ' (n.s.)'} |"
        )
    lines += ["", failures_note(frame, df), ""]
    note = degenerate_note(df, {"8²": METRICS["psnr8_db"], "32²": METRICS["psnr32_db"]})
    if note:
        lines += [note, ""]
    return "\n".join(lines)
