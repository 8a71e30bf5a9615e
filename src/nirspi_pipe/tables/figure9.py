"""Figure 9: 2D reconstruction quality (SSIM and PSNR against the true radiance) against the
background light (kLux), per scan method, in fog, objects at 20 cm, 100 % of the patterns.

Rows of ``figure9.csv``: scan × kLux, mean ± std (min, max) over objects × seeds of
``metrics.ssim`` and ``metrics.psnr`` (dB), the paired difference to *Basic*, and the paper's
value where its text gives one (Spiral reaches PSNR = 28 dB at the highest background; the curves
themselves are not tabulated). ``figure9.png``: two panels (SSIM, PSNR) against kLux, one line
per scan, error bars = std. From ``nirspi-run -m +experiment=figure9``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables._common import (
    SCAN_LABELS,
    SCANS,
    conditions_note,
    failures_note,
    ok_rows,
    paired_vs_basic,
    paper_reference,
    scan_by_level_rows,
    signif,
    stats,
)

__all__ = ["build"]

METRICS = {"ssim": "metrics.ssim", "psnr_db": "metrics.psnr"}
#: On an upscaled run (the device preset) the figure shows the scores on the upscaled grid.
UPSCALED = {"ssim": "metrics.upscale_ssim", "psnr_db": "metrics.upscale_psnr"}


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Figure 9 (PNG, CSV, Markdown) from a results frame into ``out_dir``: the normalised
    scores (:mod:`nirspi_pipe.metrics`), on the upscaled grid when the runs were upscaled."""
    out_dir = Path(out_dir)
    metrics = UPSCALED if all(c in frame.columns for c in UPSCALED.values()) else METRICS
    df = ok_rows(frame, [*metrics.values(), "illumination.klux"], "figure9")
    paper = paper_reference("figure9").set_index(["scan", "klux"])
    rows = []
    for klux in sorted(df["illumination.klux"].unique()):
        dk = df[df["illumination.klux"] == klux]
        for scan in SCANS:
            g = dk[dk["scan"] == scan]
            if g.empty:
                continue
            row: dict = {"scan": scan, "klux": float(klux), "n": int(len(g))}
            for key, col in metrics.items():
                row.update(stats(g[col], key))
                d, se, _ = paired_vs_basic(dk, col, scan)
                row.update({f"{key}_d_vs_basic": d, f"{key}_se_vs_basic": se})
                idx = (scan, float(klux))
                row[f"paper_{key}"] = float(paper.loc[idx, key]) if idx in paper.index else np.nan
            rows.append(row)
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "figure9.csv", index=False, float_format="%.6g")
    (out_dir / "figure9.md").write_text(_markdown(table, frame, df, paper))
    _plot(table, paper, out_dir / "figure9.png")
    return table


def _markdown(table: pd.DataFrame, frame: pd.DataFrame, df: pd.DataFrame, paper: pd.DataFrame) -> str:
    levels = sorted(table["klux"].unique())
    lines = [
        "# Figure 9: 2D image quality against background light, 3 µm fog, 20 cm",
        "",
        "Each cell: SSIM / PSNR (dB), mean ± std over objects × seeds; † marks a paired "
        "difference to Basic (same objects, seeds and kLux) beyond two standard errors.",
        "",
    ]
    lines += scan_by_level_rows(
        table,
        levels,
        lambda r: (
            f"{r['ssim_mean']:.3f} ± {r['ssim_std']:.3f}{signif(r['ssim_d_vs_basic'], r['ssim_se_vs_basic'])}"
            f" / {r['psnr_db_mean']:.2f} ± "
            f"{r['psnr_db_std']:.2f}{signif(r['psnr_db_d_vs_basic'], r['psnr_db_se_vs_basic'])}"
        ),
    )
    hi = table[table["klux"] == levels[-1]].sort_values("psnr_db_mean", ascending=False)
    lines += [
        "",
        f"At the highest level ({levels[-1]:g} kLux) the best PSNR is {SCAN_LABELS[hi.iloc[0]['scan']]}'s "
        f"({hi.iloc[0]['psnr_db_mean']:.2f} dB); the spread between scan means is "
        f"{hi['psnr_db_mean'].max() - hi['psnr_db_mean'].min():.3f} dB, against a std over objects × seeds "
        f"of {hi['psnr_db_std'].mean():.2f} dB.",
    ]
    for (scan, klux), p in paper.iterrows():
        vals = ", ".join(f"{k} = {p[k]:g}" for k in ("ssim", "psnr_db") if np.isfinite(p.get(k, np.nan)))
        if vals:
            lines.append(f"Paper (text of §7): {SCAN_LABELS.get(scan, scan)} at {klux:g} kLux: {vals}.")
    lines += ["", f"Rows: {conditions_note(df)}; {failures_note(frame, df)}"]
    return "\n".join(lines) + "\n"


def _plot(table: pd.DataFrame, paper: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    levels = np.sort(table["klux"].unique())
    span = float(levels[-1] - levels[0]) if len(levels) > 1 else 1.0
    for ax, key, label in zip(axes, ("ssim", "psnr_db"), ("(a) SSIM", "(b) PSNR (dB)"), strict=True):
        for i, scan in enumerate(SCANS):
            t = table[table["scan"] == scan].sort_values("klux")
            if t.empty:
                continue
            x = t["klux"].to_numpy() + (i - 1.5) * 0.008 * span  # small offsets keep error bars apart
            ax.errorbar(x, t[f"{key}_mean"], yerr=t[f"{key}_std"], marker="o", capsize=3, label=SCAN_LABELS[scan])
        pts = paper[key].dropna() if key in paper else pd.Series(dtype=float)
        for (scan, klux), v in pts.items():
            ax.plot([klux], [v], "k*", markersize=12, label=f"paper: {SCAN_LABELS.get(scan, scan)}")
        ax.set_xlabel("background light (kLux)")
        ax.set_title(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Figure 9: 2D reconstruction in fog at 20 cm, 100 % of the patterns", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
