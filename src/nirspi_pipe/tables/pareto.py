"""Table ``pareto``: reconstruction accuracy against reconstruction time (issue #4).

From a sweep over solver × scan × ratio × resolution × scene, each configuration (solver, scan,
ratio, resolution) is summarised over the scenes: mean PSNR (dB), mean SSIM and the median
solver time (``timings_ms.solver``, ms). A configuration is on the *Pareto front* of its
(resolution, ratio) when no other configuration there is at least as fast and at least as
accurate, and strictly better in one. Fronts are per resolution because the PSNR of a 32² and
a 256² image score different problems, and per ratio because the ratio is the acquisition
budget (measurement time), fixed before reconstruction starts: the front says what accuracy
each extra millisecond of computing buys from the same measurements.

Writes ``pareto.csv`` (one row per configuration, flags ``front_psnr``/``front_ssim``),
``pareto.md`` (each front as steps: what each gain in PSNR costs in time) and ``pareto.png``
(PSNR and SSIM against time, log scale, fronts drawn).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.tables._common import degenerate_mask

__all__ = ["build", "summarise", "pareto_front", "front_steps"]

RES_KEYS = ("camera.resolution",)
RATIO_KEYS = ("scan.ratio",)


def _column(frame: pd.DataFrame, keys: tuple[str, ...], default: float | None = None) -> pd.Series:
    for key in keys:
        if key in frame.columns:
            return frame[key]
    if default is None:
        raise ValueError(f"results have none of the columns {list(keys)}; sweep over them")
    return pd.Series(default, index=frame.index)


def summarise(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per (solver, scan, ratio, resolution): scenes, mean PSNR/SSIM over the jobs that
    were not left out as degenerate, how many were (``degenerate``), median time (ms)."""
    ok = frame[frame["status"] == "ok"] if "status" in frame.columns else frame
    data = pd.DataFrame(
        {
            "solver": ok["solver"],
            "scan": ok["scan"],
            "ratio": pd.to_numeric(_column(ok, RATIO_KEYS, 1.0)),
            "resolution": pd.to_numeric(_column(ok, RES_KEYS, 64)).astype(int),
            "scene": ok["scene"] if "scene" in ok.columns else "?",
            "psnr_db": pd.to_numeric(_score(ok, "metrics.psnr")).replace([np.inf], 100.0),
            "ssim": pd.to_numeric(_score(ok, "metrics.ssim")),
            "degenerate": degenerate_mask(ok, "metrics.psnr").astype(int),
            "time_ms": pd.to_numeric(ok["timings_ms.solver"]),
        }
    )
    keys = ["resolution", "solver", "scan", "ratio"]
    out = (
        data.groupby(keys)
        .agg(
            scenes=("scene", "nunique"),
            psnr_db=("psnr_db", "mean"),
            psnr_min_db=("psnr_db", "min"),
            ssim=("ssim", "mean"),
            degenerate=("degenerate", "sum"),
            time_ms=("time_ms", "median"),
        )
        .reset_index()
    )
    return out


def _score(frame: pd.DataFrame, col: str) -> pd.Series:
    """A normalised score's column; all NaN when every job left it out as degenerate."""
    return frame[col] if col in frame.columns else pd.Series(np.nan, index=frame.index)


def pareto_front(time_ms: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Boolean mask of the non-dominated points (minimise time, maximise score)."""
    t, s = np.asarray(time_ms, dtype=float), np.asarray(score, dtype=float)
    order = np.lexsort((-s, t))  # by time, best score first among equal times
    mask = np.zeros(t.size, dtype=bool)
    best = -np.inf
    for i in order:
        if np.isfinite(s[i]) and s[i] > best:
            mask[i] = True
            best = s[i]
    return mask


def front_steps(table: pd.DataFrame, metric: str = "psnr_db") -> pd.DataFrame:
    """The PSNR front of each resolution as steps: gain in the metric and the time factor paid
    for it from the previous front point."""
    rows = []
    for (res, ratio), group in table[table[f"front_{metric.split('_')[0]}"]].groupby(["resolution", "ratio"]):
        g = group.sort_values("time_ms")
        prev = None
        for _, r in g.iterrows():
            row = {
                "resolution": res,
                "ratio": ratio,
                "config": f"{r['solver']} / {r['scan']}",
                "time_ms": r["time_ms"],
                metric: r[metric],
                "gain": np.nan if prev is None else r[metric] - prev[metric],
                "time_factor": np.nan if prev is None else r["time_ms"] / max(prev["time_ms"], 1e-9),
            }
            rows.append(row)
            prev = r
    return pd.DataFrame(rows)


def _markdown(df: pd.DataFrame, floatfmt: str = ".3g") -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        cells = [format(v, floatfmt) if isinstance(v, float) else str(v) for v in r.tolist()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _plot(table: pd.DataFrame, path: Path) -> None:
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (76 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (314 ms here)

    solvers = sorted(table["solver"].unique())
    resolutions = sorted(table["resolution"].unique())
    ratios = sorted(table["ratio"].unique())
    colours = {s: plt.cm.tab10(i % 10) for i, s in enumerate(solvers)}
    markers = dict(zip(resolutions, "os^Dv<>p"))
    fig, axes = plt.subplots(2, len(ratios), figsize=(3.4 * len(ratios), 6.4), squeeze=False)
    for col, ratio in enumerate(ratios):
        at = table[table["ratio"] == ratio]
        for row, (metric, flag, label) in enumerate(
            (("psnr_db", "front_psnr", "PSNR (dB)"), ("ssim", "front_ssim", "SSIM"))
        ):
            ax = axes[row, col]
            for (solver, res), g in at.groupby(["solver", "resolution"]):
                ax.scatter(g["time_ms"], g[metric], s=14, alpha=0.6, color=colours[solver], marker=markers[res])
            for res in resolutions:
                f = at[(at["resolution"] == res) & at[flag]].sort_values("time_ms")
                ax.step(f["time_ms"], f[metric], where="post", color="black", lw=0.9)
                ax.scatter(f["time_ms"], f[metric], s=42, facecolors="none", edgecolors="black", marker=markers[res])
            ax.set_xscale("log")
            ax.grid(True, which="both", alpha=0.3)
            if row == 0:
                ax.set_title(f"{ratio:.0%} of the patterns", fontsize=9)
            if row == 1:
                ax.set_xlabel("solver time (ms)")
            if col == 0:
                ax.set_ylabel(f"{label}, mean over scenes")
    handles = [plt.Line2D([], [], ls="", marker="o", color=colours[s], label=s) for s in solvers]
    handles += [plt.Line2D([], [], ls="", marker=markers[r], color="gray", label=f"{r}²") for r in resolutions]
    handles.append(plt.Line2D([], [], color="black", label="Pareto front"))
    axes[1, -1].legend(handles=handles, fontsize=7, loc="lower right")
    fig.suptitle("Accuracy costs time: solver × scan × ratio × resolution", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Write ``pareto.csv``, ``pareto.md`` and ``pareto.png`` into ``out_dir``; return the table."""
    table = summarise(frame)
    table["front_psnr"] = False
    table["front_ssim"] = False
    for _, idx in table.groupby(["resolution", "ratio"]).groups.items():
        sub = table.loc[idx]
        table.loc[idx, "front_psnr"] = pareto_front(sub["time_ms"].to_numpy(), sub["psnr_db"].to_numpy())
        table.loc[idx, "front_ssim"] = pareto_front(sub["time_ms"].to_numpy(), sub["ssim"].to_numpy())
    out_dir = Path(out_dir)
    table.to_csv(out_dir / "pareto.csv", index=False)
    steps = front_steps(table)
    text = [
        "# Pareto: accuracy against reconstruction time",
        "",
        "Per resolution and sampling ratio, the configurations no other beats on both PSNR and",
        "solver time. `gain` is the PSNR (dB) bought by a step along the front and `time_factor`",
        "what it costs (× solver time).",
        "",
        _markdown(steps) if len(steps) else "(no successful runs)",
        "",
    ]
    bad = table[table["degenerate"] > 0] if len(table) else table
    if len(bad):
        text += [
            f"Degenerate scores: {int(bad['degenerate'].sum())} jobs in {len(bad)} configurations left their "
            'normalised PSNR/SSIM out (docs/paper.md, "Metrics"; column `degenerate`): their means are over '
            "the other scenes, NaN (not on any front) where none is left.",
            "",
        ]
    (out_dir / "pareto.md").write_text("\n".join(text))
    if len(table):
        _plot(table, out_dir / "pareto.png")
    return table
