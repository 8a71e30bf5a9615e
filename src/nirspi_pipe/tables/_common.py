"""Helpers shared by the §7 builders (Tables 3–7, Figure 9): row selection, per-scan statistics,
paired differences between scan methods, the paper's numbers, and writing/plotting.

Statistics. Every number is a mean over the jobs of one scan method (and condition) — objects ×
seeds (× kLux where a table pools them) — with its sample standard deviation (``ddof = 1``),
minimum, maximum and count. The experiments share seeds across scan methods, so the four scans of
one (object, seed, kLux) see the same noise and the same background/fog trajectories in time: the
difference to the *Basic* scan is paired. ``d_vs_basic`` is the mean paired difference and
``se_vs_basic`` its naive standard error (``std/√n``, the pairs treated as independent; kept for
the CI reference tables). The figures the Markdown prints come from :mod:`nirspi_pipe.stats`:
each cell's standard error clustered by seed (``<key>_se``, ``<key>_clusters``), the paired
difference's standard error clustered by seed (``<key>_se_cl_vs_basic``), and a ranking claim only
where it holds after Holm's correction on both halves of the seeds (:func:`ranking`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from nirspi_pipe import stats as st
from nirspi_pipe.metrics import DEGENERATE_FLAG, NO_CONTENT_FLAG

__all__ = [
    "SCANS",
    "SCAN_LABELS",
    "ok_rows",
    "stats",
    "paired_vs_basic",
    "paper_reference",
    "fmt",
    "signif",
    "failures_note",
    "conditions_note",
    "bar_figure",
    "save_figure",
    "cell",
    "ranking",
    "ranking_note",
    "with_families",
    "score_flag_columns",
    "degenerate_mask",
    "degenerate_count",
    "fmt_scored",
    "degenerate_note",
    "scan_groups",
    "klux_levels",
    "compared_row",
    "column_rankings",
    "column_notes",
    "rows_note",
    "write_csv",
]

#: The paper's four scan methods, in its row order.
SCANS = ("basic", "hilbert", "zigzag", "spiral")
SCAN_LABELS = {"basic": "Basic", "hilbert": "Hilbert", "zigzag": "Zig-Zag", "spiral": "Spiral"}
#: Columns that identify one paired sample (present ones are used).
PAIR_KEYS = ("scene", "seed", "illumination.klux")


def ok_rows(frame: pd.DataFrame, need: list[str], experiment: str) -> pd.DataFrame:
    """The successful rows of ``frame`` whose scan is one of :data:`SCANS`.

    Raises ``ValueError`` naming the experiment to run when a needed column is missing (the frame
    did not come from that sweep) or when no row is usable.
    """
    # a normalised score that every job left out as degenerate has no column, only its flags
    absent = [c for c in need if c not in frame.columns and any(f in frame.columns for f in score_flag_columns(c))]
    if absent:
        frame = frame.assign(**{c: np.nan for c in absent})
    missing = [c for c in ["scan", *need] if c not in frame.columns]
    if missing:
        raise ValueError(f"needs columns {missing}: run `nirspi-run -m +experiment={experiment}`")
    df = frame[frame["status"] == "ok"] if "status" in frame.columns else frame
    df = df[df["scan"].isin(SCANS)].copy()
    if df.empty:
        raise ValueError(f"no successful job of the four scan methods: run `nirspi-run -m +experiment={experiment}`")
    return df


def scan_groups(df: pd.DataFrame) -> Iterator[tuple[str, pd.DataFrame]]:
    """``(scan, rows)`` for each of :data:`SCANS` (in the paper's order) that ``df`` has rows of."""
    for scan in SCANS:
        g = df[df["scan"] == scan]
        if not g.empty:
            yield scan, g


def klux_levels(df: pd.DataFrame) -> Iterator[tuple[Any, pd.DataFrame]]:
    """``(level, rows)`` for each background light level of ``df`` (``illumination.klux``), ascending."""
    for klux in sorted(df["illumination.klux"].unique()):
        yield klux, df[df["illumination.klux"] == klux]


def write_csv(table: pd.DataFrame, path: Path) -> None:
    """A table builder's CSV: no index, six significant digits."""
    table.to_csv(path, index=False, float_format="%.6g")


#: A normalised score's column (``metrics.<prefix>psnr`` / ``ssim``).
_SCORE = re.compile(r"^metrics\.(?P<prefix>\w*?)(?:psnr|ssim)$")


def score_flag_columns(col: str) -> list[str]:
    """The flag columns that mark ``col`` left out as degenerate (:func:`nirspi_pipe.metrics.content_test`):
    ``metrics.<prefix>degenerate_reference`` and ``…degenerate_image`` of a normalised PSNR/SSIM,
    both prefixes' for the gain over bicubic; none for other columns."""
    if col == "metrics.upscale_gain_db":
        prefixes = ["upscale_", "bicubic_"]
    else:
        m = _SCORE.match(col)
        if m is None:
            return []
        prefixes = [m.group("prefix")]
    return [f"metrics.{p}{f}" for p in prefixes for f in (DEGENERATE_FLAG, NO_CONTENT_FLAG)]


def degenerate_mask(frame: pd.DataFrame, col: str) -> pd.Series:
    """Rows of ``frame`` whose ``col`` was left out as degenerate (a flag set, no value)."""
    flags = [c for c in score_flag_columns(col) if c in frame.columns]
    if not flags:
        return pd.Series(False, index=frame.index)
    flagged = frame[flags].apply(pd.to_numeric, errors="coerce").fillna(0.0).gt(0.0).any(axis=1)
    empty = pd.to_numeric(frame[col], errors="coerce").isna() if col in frame.columns else True
    return flagged & empty


def degenerate_count(group: pd.DataFrame, col: str, key: str) -> dict[str, int]:
    """``{key}_degenerate``: how many of ``group``'s rows left ``col`` out as degenerate (its
    :func:`stats` are over the others)."""
    return {f"{key}_degenerate": int(degenerate_mask(group, col).sum())}


def fmt_scored(mean: float, spread: float, degenerate: float, n: float, digits: int = 2) -> str:
    """A cell of a normalised score: ``degenerate`` when all ``n`` rows were, else :func:`fmt`
    with ``‡k`` when ``k`` of them were left out of the mean (:func:`degenerate_note`)."""
    k = int(degenerate) if np.isfinite(degenerate) else 0
    if k and k >= n:
        return "degenerate"
    return fmt(mean, spread, digits) + (f" ‡{k}" if k else "")


def degenerate_note(df: pd.DataFrame, cols: dict[str, str]) -> str:
    """One sentence on the rows whose normalised scores were left out as degenerate (label ->
    column), with their flags; empty when there are none."""
    parts = []
    for label, col in cols.items():
        mask = degenerate_mask(df, col)
        if not mask.any():
            continue
        why = []
        for flag in (DEGENERATE_FLAG, NO_CONTENT_FLAG):
            cs = [c for c in score_flag_columns(col) if c.endswith(flag) and c in df.columns]
            k = (
                int((mask & df[cs].apply(pd.to_numeric, errors="coerce").fillna(0.0).gt(0.0).any(axis=1)).sum())
                if cs
                else 0
            )
            if k:
                why.append(f"{k}× {flag}")
        parts.append(f"{label} ({col}): {int(mask.sum())} of {len(df)} jobs ({', '.join(why)})")
    if not parts:
        return ""
    return (
        "Degenerate scores, left out of every mean, standard error and paired difference (docs/paper.md, "
        '"Metrics"; ‡k in a cell: k of its jobs left out; "degenerate": all of them): ' + "; ".join(parts) + "."
    )


def stats(values: pd.Series | np.ndarray, prefix: str) -> dict[str, float]:
    """``{prefix_mean, prefix_std, prefix_min, prefix_max}`` of the finite values (NaN if none);
    the std is the sample std (ddof = 1), 0 for a single value."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {f"{prefix}_{k}": np.nan for k in ("mean", "std", "min", "max")}
    return {
        f"{prefix}_mean": float(v.mean()),
        f"{prefix}_std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
        f"{prefix}_min": float(v.min()),
        f"{prefix}_max": float(v.max()),
    }


def paired_vs_basic(df: pd.DataFrame, metric: str, scan: str) -> tuple[float, float, int]:
    """Mean and standard error of ``metric(scan) − metric(basic)`` over the samples both scans have
    (paired on scene, seed and kLux), and the number of pairs. ``(0, 0, n)`` for ``basic`` itself;
    the standard error is NaN with fewer than two pairs."""
    keys = [k for k in PAIR_KEYS if k in df.columns]
    sub = df[df["scan"].isin(["basic", scan])]
    if not keys:
        return np.nan, np.nan, 0
    wide = sub.pivot_table(index=keys, columns="scan", values=metric, aggfunc="mean")
    if "basic" not in wide or scan not in wide:
        return np.nan, np.nan, 0
    d = (wide[scan] - wide["basic"]).to_numpy(dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return np.nan, np.nan, 0
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else np.nan
    return float(d.mean()), se, int(d.size)


def compare_metric(
    df: pd.DataFrame, group: pd.DataFrame, scan: str, key: str, col: str, paper: pd.DataFrame
) -> dict[str, float]:
    """One scan's cells for metric ``col``: its :func:`stats` over ``group`` (prefixed ``key``),
    the paper's value ``paper.loc[scan, key]``, the difference, and the paired difference to
    Basic over ``df`` with its standard error."""
    summary = stats(group[col], key)
    d, se, _ = paired_vs_basic(df, col, scan)
    p = float(paper.loc[scan, key]) if scan in paper.index else np.nan
    se_cl = st.paired_difference(df, col, scan, "basic")["se"] if scan != "basic" else 0.0
    return {
        **summary,
        f"paper_{key}": p,
        f"diff_{key}": summary[f"{key}_mean"] - p,
        f"{key}_d_vs_basic": d,
        f"{key}_se_vs_basic": se,
        **cell(group, col, key),
        f"{key}_se_cl_vs_basic": se_cl,
    }


def compared_row(df: pd.DataFrame, scan: str, g: pd.DataFrame, columns: dict[str, str], paper: pd.DataFrame) -> dict:
    """One scan's row of a table comparing metrics with the paper: ``scan``, ``n`` (rows of
    ``g``) and :func:`compare_metric` of each ``key -> column`` of ``columns``."""
    row: dict = {"scan": scan, "n": int(len(g))}
    for key, col in columns.items():
        row.update(compare_metric(df, g, scan, key, col, paper))
    return row


def cell(group: pd.DataFrame, col: str, key: str) -> dict[str, float]:
    """``{key}_se`` (the cell mean's standard error clustered by seed) and ``{key}_clusters`` (the
    number of seeds) of column ``col`` over one table cell's rows (:func:`nirspi_pipe.stats.cell_summary`)."""
    c = st.cell_summary(group, col, prefix=key)
    return {f"{key}_se": c[f"{key}_se"], f"{key}_clusters": c[f"{key}_clusters"]}


def ranking(df: pd.DataFrame, col: str, higher_is_better: bool, where: dict | None = None) -> pd.DataFrame:
    """The four scans' pairwise comparisons of ``col`` over ``df`` (paired on scene, seed and kLux,
    clustered by seed, Holm-corrected, replicated on both seed halves:
    :func:`nirspi_pipe.stats.replicated_claims`), with the columns of ``where`` (the cell's
    condition) added."""
    out = st.replicated_claims(df, col, list(SCANS), higher_is_better=higher_is_better)
    for k, v in (where or {}).items():
        out.insert(0, k, v)
    return out


def column_rankings(df: pd.DataFrame, columns: dict[str, str], higher_is_better: Callable[[str], bool]) -> pd.DataFrame:
    """:func:`ranking` of each ``key -> column`` of ``columns`` over ``df`` (its family named in
    the ``column`` column), corrected across the families (:func:`nirspi_pipe.stats.across_families`)."""
    claims = pd.concat(
        [
            ranking(df, col, higher_is_better=higher_is_better(key), where={"column": key})
            for key, col in columns.items()
        ],
        ignore_index=True,
    )
    return st.across_families(claims)


def column_notes(claims: pd.DataFrame) -> str:
    """The replicated claims of each family of :func:`column_rankings`, as ``key: claims; …``."""
    return "; ".join(f"{key}: {ranking_note(c)}" for key, c in claims.groupby("column", sort=False))


def ranking_note(claims: pd.DataFrame) -> str:
    """The replicated claims of one family as text (``none`` when no claim holds)."""
    return st.claims_sentence(claims, SCAN_LABELS)


def with_families(markdown: str, claims: pd.DataFrame) -> str:
    """``markdown`` with a closing paragraph on what is controlled across the table's families
    (:func:`nirspi_pipe.stats.family_sentence`; ``claims`` from :func:`nirspi_pipe.stats.across_families`)."""
    return markdown.rstrip("\n") + "\n\n**Across families.** " + st.family_sentence(claims) + "\n"


def scan_by_level_rows(table: pd.DataFrame, levels: list[float], cell: Callable[[pd.Series], str]) -> list[str]:
    """Markdown table lines: a header of kLux ``levels``, then one row per scan whose cells are
    ``cell(row)`` for that scan and level (``n/a`` where the table has no such row)."""
    lines = [
        "| Scanning method | " + " | ".join(f"{k:g} kLux" for k in levels) + " |",
        "|---|" + "---:|" * len(levels),
    ]
    for scan in SCANS:
        cells = []
        for k in levels:
            r = table[(table["scan"] == scan) & (table["klux"] == k)]
            cells.append("n/a" if r.empty else cell(r.iloc[0]))
        lines.append(f"| {SCAN_LABELS[scan]} | " + " | ".join(cells) + " |")
    return lines


def paper_reference(name: str) -> pd.DataFrame:
    """The paper's numbers for table ``name`` (``experiments/reference/<name>.csv``, installed)."""
    path = Path(str(resources.files("nirspi_pipe.experiments"))) / "reference" / f"{name}.csv"
    return pd.read_csv(path)


def fmt(mean: float, std: float, digits: int = 2) -> str:
    """``"m ± s"`` (``"n/a"`` for NaN)."""
    if not np.isfinite(mean):
        return "n/a"
    return f"{mean:.{digits}f} ± {std:.{digits}f}" if np.isfinite(std) else f"{mean:.{digits}f}"


def signif(d: float, se: float) -> str:
    """``"†"`` when a paired difference is more than two standard errors from 0."""
    return "†" if np.isfinite(d) and np.isfinite(se) and se > 0 and abs(d) > 2 * se else ""


def failures_note(frame: pd.DataFrame, used: pd.DataFrame) -> str:
    """One sentence on how many jobs the table used and how many failed (never silently dropped)."""
    total = int(frame["scan"].isin(SCANS).sum()) if "scan" in frame.columns else len(frame)
    bad = total - len(used)
    note = f"{len(used)} successful jobs"
    if bad:
        errs = (
            frame.loc[frame["status"] != "ok", "error"].dropna().astype(str)
            if "error" in frame
            else pd.Series([], dtype=str)
        )
        top = errs.value_counts().head(2)
        note += f"; {bad} failed or missing, left out" + (
            " (" + "; ".join(f"{n}× {e[:90]}" for e, n in top.items()) + ")" if len(top) else ""
        )
    return note + "."


def rows_note(df: pd.DataFrame, frame: pd.DataFrame) -> str:
    """The Markdown's last line: the conditions ``df`` (the rows used) covers and how many of
    ``frame``'s jobs it used (:func:`conditions_note`, :func:`failures_note`)."""
    return f"Rows: {conditions_note(df)}; {failures_note(frame, df)}"


def conditions_note(df: pd.DataFrame) -> str:
    """Objects, seeds and kLux levels that the rows cover."""
    parts = []
    if "scene" in df.columns:
        parts.append("objects " + ", ".join(sorted(map(str, df["scene"].dropna().unique()))))
    if "seed" in df.columns:
        parts.append(f"{df['seed'].nunique()} seeds")
    if "illumination.klux" in df.columns:
        parts.append(
            "background " + ", ".join(f"{k:g}" for k in sorted(df["illumination.klux"].dropna().unique())) + " kLux"
        )
    return "; ".join(parts)


def count_range(n: pd.Series) -> str:
    """``"160"`` or ``"150–160"``: the range of per-cell counts, for captions."""
    lo, hi = int(n.min()), int(n.max())
    return f"{lo}" if lo == hi else f"{lo}–{hi}"


#: Hatchings of the paper's bars in :func:`bar_figure`, one per paper series (in order).
PAPER_HATCHES = ("//", "\\\\", "xx", "..", "--")


def save_figure(path: Path, fig: Any, dpi: int = 100) -> None:
    """Write a builder's figure as a PNG (tight, with a small margin) and close it."""
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (267 ms here)

    fig.savefig(path, dpi=dpi, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def bar_figure(
    title: str,
    groups: list[str],
    series: dict[str, tuple[list[float], list[float]]],
    paper: dict[str, list[float]] | None,
    ylabel: str,
    errbars: str,
) -> Any:
    """Grouped bars (one group per scan method): ours (mean, error bars) and the paper's values
    (hatched), as a matplotlib figure (:func:`save_figure` writes and closes it). ``errbars`` says
    what the error bars are; it is printed under the plot. The legend sits right of the axes,
    where it covers no bar (issue 34). Each paper series is hatched in its own pattern
    (:data:`PAPER_HATCHES`) and outlined in the colour of our series of the same name."""
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (76 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (267 ms here)

    names = list(series)
    k = len(names) + (len(paper) if paper else 0)
    width = 0.8 / max(k, 1)
    x = np.arange(len(groups))
    fig, ax = plt.subplots(figsize=(8, 4.2), layout="constrained")
    i = 0
    colours: dict[str, Any] = {}
    for name in names:
        mean, err = series[name]
        bars = ax.bar(x + (i - (k - 1) / 2) * width, mean, width, yerr=err, capsize=3, label=f"ours: {name}")
        colours[name] = bars.patches[0].get_facecolor() if bars.patches else None
        i += 1
    for j, (name, vals) in enumerate((paper or {}).items()):
        # each paper series its own hatching, outlined in the colour of our series of that name:
        # two paper entries with one hatching could not be told apart in the legend (issue 43)
        edge = colours.get(name) or "black"
        hatch = PAPER_HATCHES[j % len(PAPER_HATCHES)]
        ax.bar(
            x + (i - (k - 1) / 2) * width, vals, width, fill=False, hatch=hatch, edgecolor=edge, label=f"paper: {name}"
        )
        i += 1
    ax.set_xticks(x)
    ax.set_xticklabels(groups)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.text(0.01, 0.0, errbars, fontsize=7, ha="left", va="top", wrap=True)
    return fig
