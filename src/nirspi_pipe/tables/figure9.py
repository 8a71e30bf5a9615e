"""Figure 9: 2D reconstruction quality (SSIM and PSNR against the true radiance) against the
background light (kLux), per scan method, in fog, objects at 20 cm, 100 % of the patterns.

Rows of ``figure9.csv``: scan × kLux, mean ± std (min, max) over objects × seeds of
``metrics.ssim`` and ``metrics.psnr`` (dB), the paired difference to *Basic*, and the paper's
value where its text gives one (Spiral reaches PSNR = 28 dB at the highest background; the curves
themselves are not tabulated). ``figure9.png``: two panels (SSIM, PSNR) against kLux, one line
per scan, error bars = std. From ``nirspi-run -m +experiment=figure9``.

Per object (``figure9_objects.csv``, ``figure9_objects.png``, the Markdown; sphere first: the
objects' resolution ceilings differ, so pooling them mixes four different curves), three PSNR
scores, each mean ± standard error clustered by seed (:mod:`nirspi_pipe.stats`):

* ``psnr32``: the upscaled 32² image against the scene rendered at 32² (``metrics.upscale_psnr``;
  resolution-limited: a noise-free 8² image upscaled scores well below the cap);
* ``noise32``: the upscaled image against the upscaler applied to the camera's noise-free 8²
  image (``metrics.noise_psnr``): the cost of noise, wander and fog fluctuation alone at 32²;
* ``psnr8``: the camera's 8² reconstruction against its noise-free image (``metrics.psnr``).

``figure9_rankings.csv``: every pairwise comparison of the scans per object, kLux and score
(paired on seed, Holm over the six pairs, both seed halves); the Markdown states only the claims
that hold in both halves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe import stats as st
from nirspi_pipe.tables import _common as common

__all__ = ["build"]

METRICS = {"ssim": "metrics.ssim", "psnr_db": "metrics.psnr"}
#: On an upscaled run (the device preset) the figure shows the scores on the upscaled grid.
UPSCALED = {"ssim": "metrics.upscale_ssim", "psnr_db": "metrics.upscale_psnr"}
#: The three per-object scores (module docstring): key -> record column.
SCORES = {"psnr32": "metrics.upscale_psnr", "noise32": "metrics.noise_psnr", "psnr8": "metrics.psnr"}
SCORE_LABELS = {
    "psnr32": "32² vs truth (resolution-limited)",
    "noise32": "32² noise-only",
    "psnr8": "8² camera image",
}
OBJECTS = ("sphere", "torus", "cube", "u_shape")


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Figure 9 (PNG, CSV, Markdown) from a results frame into ``out_dir``: the normalised
    scores (:mod:`nirspi_pipe.metrics`), on the upscaled grid when the runs were upscaled."""
    out_dir = Path(out_dir)
    metrics = _pooled(frame)
    df = common.ok_rows(frame, [*metrics.values(), "illumination.klux"], "figure9")
    paper = common.paper_reference("figure9").set_index(["scan", "klux"])
    rows = []
    for klux, dk in common.klux_levels(df):
        for scan, g in common.scan_groups(dk):
            row: dict = {"scan": scan, "klux": float(klux), "n": int(len(g))}
            for key, col in metrics.items():
                row.update(common.stats(g[col], key))
                row.update(common.degenerate_count(g, col, key))
                d, se, _ = common.paired_vs_basic(dk, col, scan)
                row.update({f"{key}_d_vs_basic": d, f"{key}_se_vs_basic": se})
                idx = (scan, float(klux))
                row[f"paper_{key}"] = float(paper.loc[idx, key]) if idx in paper.index else np.nan
            for key, col in metrics.items():
                row.update(common.cell(g, col, key))
            rows.append(row)
    table = pd.DataFrame(rows)
    common.write_csv(table, out_dir / "figure9.csv")
    scores = {k: c for k, c in SCORES.items() if c in df.columns and df[c].notna().any()}
    objects, claims = _per_object(df, scores)
    if len(objects):
        common.write_csv(objects, out_dir / "figure9_objects.csv")
        claims = st.across_families(claims)
        common.write_csv(claims, out_dir / "figure9_rankings.csv")
        _plot_objects(objects, scores, paper, out_dir / "figure9_objects.png")
    (out_dir / "figure9.md").write_text(
        common.with_families(_markdown(table, frame, df, paper, objects, claims, scores), claims)
    )
    _plot(table, paper, out_dir / "figure9.png")
    return table


def _pooled(frame: pd.DataFrame) -> dict[str, str]:
    """The pooled figure's columns: the upscaled scores when the runs were upscaled (a score that
    every job left out as degenerate has only its flag columns), else the camera's."""
    have = [
        c in frame.columns or any(f in frame.columns for f in common.score_flag_columns(c)) for c in UPSCALED.values()
    ]
    return UPSCALED if all(have) else METRICS


def _order(names: list[str]) -> list[str]:
    known = [o for o in OBJECTS if o in names]
    return known + sorted(n for n in names if n not in OBJECTS)


def _per_object(df: pd.DataFrame, scores: dict[str, str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Rows per object × kLux × scan with each score's mean, clustered SE and n, and the ranking
    families per object × kLux × score."""
    if "scene" not in df.columns or not scores:
        return pd.DataFrame(), pd.DataFrame()
    rows, fams = [], []
    for scene in _order(list(df["scene"].dropna().unique())):
        for klux, dk in common.klux_levels(df[df["scene"] == scene]):
            for scan, g in common.scan_groups(dk):
                row: dict = {"scene": scene, "klux": float(klux), "scan": scan, "n": int(len(g))}
                for key, col in scores.items():
                    row[f"{key}_mean"] = float(g[col].mean())
                    row.update(common.cell(g, col, key))
                    row.update(common.degenerate_count(g, col, key))
                rows.append(row)
            for key, col in scores.items():
                fams.append(common.ranking(dk, col, True, where={"scene": scene, "klux": float(klux), "score": key}))
    return pd.DataFrame(rows), (pd.concat(fams, ignore_index=True) if fams else pd.DataFrame())


def _object_cell(o: pd.DataFrame, scan: str, k: float, scores: dict[str, str]) -> str:
    """One per-object cell: each score's mean ± standard error and the seed count, or n/a."""
    r = o[(o["scan"] == scan) & (o["klux"] == k)]
    if r.empty:
        return "n/a"
    r0 = r.iloc[0]
    return (
        " / ".join(
            common.fmt_scored(r0[f"{key}_mean"], r0[f"{key}_se"], r0[f"{key}_degenerate"], r0["n"]) for key in scores
        )
        + f" (n={int(r0['n'])})"
    )


def _object_section(
    scene: str, objects: pd.DataFrame, claims: pd.DataFrame, levels: list[float], scores: dict[str, str]
) -> list[str]:
    """One object's table (scan by light level) and its replicated rankings."""
    o = objects[objects["scene"] == scene]
    lines = [
        f"### {scene}",
        "",
        "| scan | " + " | ".join(f"{k:g} kLux" for k in levels) + " |",
        "|---|" + "---:|" * len(levels),
    ]
    for scan in common.SCANS:
        cells = [_object_cell(o, scan, k, scores) for k in levels]
        lines.append(f"| {common.SCAN_LABELS[scan]} | " + " | ".join(cells) + " |")
    c = claims[claims["scene"] == scene]
    notes = [
        f"{k:g} kLux, {key}: {common.ranking_note(f)}"
        for (k, key), f in c.groupby(["klux", "score"], sort=False)
        if common.ranking_note(f) != "none"
    ]
    return [
        *lines,
        "",
        "Replicated rankings (Holm over the six pairs, both seed halves): "
        + ("; ".join(notes) if notes else "none")
        + ".",
        "",
    ]


def _sphere_line(objects: pd.DataFrame, scan: str, klux: float, p: pd.Series, scores: dict[str, str]) -> str | None:
    """Our sphere's scores at the paper's quoted condition, with the difference to the paper's
    PSNR; None without a sphere row or a quoted PSNR."""
    sph = (
        objects[(objects["scene"] == "sphere") & (objects["scan"] == scan) & (objects["klux"] == klux)]
        if len(objects)
        else objects
    )
    if not (len(sph) and "psnr_db" in p and np.isfinite(p["psnr_db"])):
        return None
    r0 = sph.iloc[0]
    return (
        f"Ours, sphere, {common.SCAN_LABELS.get(scan, scan)}, {klux:g} kLux: "
        + ", ".join(
            f"{SCORE_LABELS[k]} "
            + common.fmt_scored(r0[f"{k}_mean"], r0[f"{k}_se"], r0[f"{k}_degenerate"], r0["n"])
            + (
                f" dB ({r0[f'{k}_mean'] - p['psnr_db']:+.2f} dB from the paper's {p['psnr_db']:g})"
                if np.isfinite(r0[f"{k}_mean"])
                else ""
            )
            for k in scores
        )
        + "."
    )


def _paper_lines(paper: pd.DataFrame, objects: pd.DataFrame, scores: dict[str, str]) -> list[str]:
    """The paper's quoted values (text of §7), each followed by our sphere's at that condition."""
    lines: list[str] = []
    for (scan, klux), p in paper.iterrows():
        vals = ", ".join(f"{k} = {p[k]:g}" for k in ("ssim", "psnr_db") if np.isfinite(p.get(k, np.nan)))
        if vals:
            lines += ["", f"Paper (text of §7): {common.SCAN_LABELS.get(scan, scan)} at {klux:g} kLux: {vals}."]
            ours = _sphere_line(objects, scan, klux, p, scores)
            if ours is not None:
                lines.append(ours)
    return lines


def _markdown(
    table: pd.DataFrame,
    frame: pd.DataFrame,
    df: pd.DataFrame,
    paper: pd.DataFrame,
    objects: pd.DataFrame,
    claims: pd.DataFrame,
    scores: dict[str, str],
) -> str:
    levels = sorted(table["klux"].unique())
    lines = ["# Figure 9: 2D image quality against background light, 3 µm fog, 20 cm", ""]
    if len(objects):
        lines += [
            "Per object (the objects' resolution ceilings differ; sphere first). Each cell: PSNR (dB), "
            "mean ± standard error clustered by seed, for "
            + ", ".join(f"**{SCORE_LABELS[k]}**" for k in scores)
            + ". n = seeds per cell.",
            "",
        ]
        for scene in _order(list(objects["scene"].unique())):
            lines += _object_section(scene, objects, claims, levels, scores)
    lines += [
        "## Pooled over the objects (the previous figure; mixes four ceilings)",
        "",
        "Each cell: SSIM / PSNR (dB) at the figure's resolution, mean ± std over objects × seeds.",
        "",
    ]
    lines += common.scan_by_level_rows(
        table,
        levels,
        lambda r: (
            common.fmt_scored(r["ssim_mean"], r["ssim_std"], r["ssim_degenerate"], r["n"], 3)
            + " / "
            + common.fmt_scored(r["psnr_db_mean"], r["psnr_db_std"], r["psnr_db_degenerate"], r["n"])
        ),
    )
    lines += _paper_lines(paper, objects, scores)
    lines += ["", common.rows_note(df, frame)]
    note = common.degenerate_note(
        df, {**{SCORE_LABELS[k]: c for k, c in SCORES.items()}, **{f"pooled {k}": c for k, c in _pooled(df).items()}}
    )
    if note:
        lines += ["", note]
    return "\n".join(lines) + "\n"


def _plot_objects(objects: pd.DataFrame, scores: dict[str, str], paper: pd.DataFrame, path: Path) -> None:
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (75 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (271 ms here)

    scenes = _order(list(objects["scene"].unique()))
    fig, axes = plt.subplots(len(scores), len(scenes), figsize=(3.2 * len(scenes), 2.8 * len(scores)), squeeze=False)
    for j, scene in enumerate(scenes):
        for i, key in enumerate(scores):
            ax = axes[i][j]
            for scan in common.SCANS:
                t = objects[(objects["scene"] == scene) & (objects["scan"] == scan)].sort_values("klux")
                if len(t):
                    ax.errorbar(
                        t["klux"],
                        t[f"{key}_mean"],
                        yerr=t[f"{key}_se"],
                        marker="o",
                        capsize=2,
                        label=common.SCAN_LABELS[scan],
                    )
            if key == "psnr32" and j == 0 and "psnr_db" in paper:  # the paper's 28 dB, beside the sphere only
                for (_, klux), v in paper["psnr_db"].dropna().items():
                    ax.plot([klux], [v], "k*", markersize=10)
            ax.set_title(f"{scene}: {SCORE_LABELS[key]}", fontsize=8)
            ax.grid(alpha=0.3)
            if i == len(scores) - 1:
                ax.set_xlabel("kLux")
            if j == 0:
                ax.set_ylabel("PSNR (dB)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))  # room under the panels for the legend and caption
    fig.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.01, 0.02), ncol=len(labels), fontsize=7)
    fig.text(
        0.99,
        0.02,
        "Error bars: ± 1 standard error of the mean over seeds, clustered by seed; ★: the paper's 28 dB (Spiral, "
        "50 kLux).",
        fontsize=7,
        ha="right",
        va="bottom",
    )
    common.save_figure(path, fig, dpi=90)


def _plot(table: pd.DataFrame, paper: pd.DataFrame, path: Path) -> None:
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (75 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (271 ms here)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    levels = np.sort(table["klux"].unique())
    span = float(levels[-1] - levels[0]) if len(levels) > 1 else 1.0
    for ax, key, label in zip(axes, ("ssim", "psnr_db"), ("(a) SSIM", "(b) PSNR (dB)"), strict=True):
        for i, scan in enumerate(common.SCANS):
            t = table[table["scan"] == scan].sort_values("klux")
            if t.empty:
                continue
            x = t["klux"].to_numpy() + (i - 1.5) * 0.008 * span  # small offsets keep error bars apart
            ax.errorbar(
                x, t[f"{key}_mean"], yerr=t[f"{key}_std"], marker="o", capsize=3, label=common.SCAN_LABELS[scan]
            )
        pts = paper[key].dropna() if key in paper else pd.Series(dtype=float)
        for (scan, klux), v in pts.items():
            ax.plot([klux], [v], "k*", markersize=12, label=f"paper: {common.SCAN_LABELS.get(scan, scan)}")
        ax.set_xlabel("background light (kLux)")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    fig.suptitle("Figure 9: 2D reconstruction in fog at 20 cm, 100 % of the patterns", fontsize=10)
    n = common.count_range(table["n"]) if "n" in table and len(table) else "the"
    fig.tight_layout(rect=(0.0, 0.12, 1.0, 1.0))  # room under the panels for the legend and caption
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 0.055), ncol=len(labels), fontsize=8)
    fig.text(
        0.5,
        0.0,
        f"Pooled over the objects. Error bars: ± 1 standard deviation over the {n} jobs of each point (objects × "
        "seeds): mostly the spread between the objects' resolution ceilings, not the uncertainty of the mean "
        "(figure9.md and figure9_objects.png give each object's mean ± standard error clustered by seed); ★: the "
        "paper's values.",
        fontsize=7,
        ha="center",
        va="bottom",
        wrap=True,
    )
    common.save_figure(path, fig)
