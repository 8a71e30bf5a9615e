"""The 3D accuracy–time front (issue 44, item 5): chamfer and fused depth error against time over
the project's held-out shapes, noise-free and in the fog chamber.

    nice python experiments/shapes/front.py --out DIR [--full] [--shapes vase,bowl] [--seeds 0-2] [overrides…]

Other arguments are Hydra overrides for every job (``itof.ned_cm_per_sqrt_hz=0``, for example).

Sweeps resolution × SFS variant (``sfs=truth``, the oracle depth, included) × anchoring (the iToF's
averaging time ``itof.averaging_s``: 0.5 s is Table 1's σ = 1 cm per spot, 8 s a quarter of it) ×
surface (``conf/surface``) over the held-out shapes (``nirspi_pipe.scene.testshapes``) and seeds,
``itof=cw4 fusion=itof metrics=full`` with the 64² study's virtual camera (``preset=null``), in two
conditions, each one ``nirspi-run -m`` sweep under ``DIR/<condition>`` (resumable: a rerun runs only
the jobs without a record):

* ``noise_free``: ``fog=none illumination=none detector=ideal`` (the iToF at its own noise),
* ``chamber``: ``fog=chamber illumination=klux detector=ingaas`` (the default run's fog chamber,
  15 kLux and InGaAs photodiode, conf/config.yaml, at the sweep's resolution).

Then it reads the records back with :func:`nirspi_pipe.load_results` and writes, in ``DIR``:

* ``front.parquet`` / ``front.csv``: one row per configuration (condition, resolution, sfs,
  averaging, surface) with, of ``metrics.chamfer_mm`` and ``metrics.depth_rmse_fused_mm``, the
  mean over the shapes of each shape's median over the seeds (each shape weighs the same), each
  shape's median and the smallest and largest job; the median over its jobs of the computing
  time (below) and of ``timings_ms.total``; the jobs that ran ok out of the jobs swept; the
  error split by stage against the configuration's ``sfs=truth`` row; and the front flags
  ``front_chamfer`` / ``front_depth``;
* ``front.md``: the same as Markdown tables, one per condition (``front_members.md``: the
  front members only);
* ``front.png``: error against time, one panel per (condition, metric), front members ringed
  and labelled with their resolution and surface.

A configuration is on a front when no other configuration of its condition is at least as good in
the error (mean of the shapes' medians), the median computing time (``timings_ms.total`` less
``timings_ms.scene`` and ``timings_ms.metrics``: the simulator's rendering of the truth and the
scoring against it, which no camera runs; ms) and the iToF's averaging time
(``itof.averaging_s``: acquisition time the computing time does not hold), and strictly better
in one. The oracle rows (``sfs=truth``) are references for the split, never
on a front. A configuration with a failed job has no summary (never on a front).

The default grid is :data:`DEFAULT` (432 jobs, sized for about 10 minutes on an idle 2-core
machine; what it took here: docs/mesh.md, *The 3D accuracy–time front*); ``--full`` is
:data:`FULL` (hours).
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: The two conditions: overrides on top of ``preset=null`` (no device preset: the sweep's resolution).
CONDITIONS: dict[str, tuple[str, ...]] = {
    "noise_free": ("fog=none", "illumination=none", "detector=ideal"),
    "chamber": ("fog=chamber", "illumination=klux", "detector=ingaas"),
}
#: Every job's fixed overrides (the 3D path of docs/mesh.md's studies).
FIXED = ("preset=null", "itof=cw4", "fusion=itof", "metrics=full")
#: Records only: thousands of jobs.
QUIET = ("output.quiet=true", "output.arrays=false", "output.images=false")
#: The swept axes: (column in load_results' table, override key).
AXES = (
    ("camera.resolution", "camera.resolution"),
    ("sfs", "sfs"),
    ("itof.averaging_s", "itof.averaging_s"),
    ("surface", "surface"),
)
#: The metrics of the table (record keys, as load_results' columns).
CHAMFER = "metrics.chamfer_mm"
DEPTH = "metrics.depth_rmse_fused_mm"
TIME = "timings_ms.total"
#: Left out of the front's time: the simulator rendering the truth and the scores against it (a
#: camera runs neither); ``time_ms`` = ``timings_ms.total`` minus these, per job.
NOT_A_CAMERA_COST = ("timings_ms.scene", "timings_ms.metrics")
AVERAGING = "itof.averaging_s"


@dataclass(frozen=True)
class Grid:
    """One sweep's axes (each a tuple of override values)."""

    resolution: tuple[int, ...]
    sfs: tuple[str, ...]
    averaging_s: tuple[float, ...]
    surface: tuple[str, ...]
    shapes: tuple[str, ...]
    seeds: tuple[int, ...]
    conditions: tuple[str, ...] = tuple(CONDITIONS)

    def __post_init__(self) -> None:
        for name in ("resolution", "sfs", "averaging_s", "surface", "shapes", "seeds", "conditions"):
            if not getattr(self, name):
                raise ValueError(f"grid.{name}: empty; give at least one value")
        if "truth" not in self.sfs:
            raise ValueError("grid.sfs: the split by stage needs sfs=truth among the variants")
        bad = [c for c in self.conditions if c not in CONDITIONS]
        if bad:
            raise ValueError(f"grid.conditions: {bad}; allowed: {sorted(CONDITIONS)}")

    def configurations(self) -> int:
        """Configurations per condition."""
        return len(self.resolution) * len(self.sfs) * len(self.averaging_s) * len(self.surface)

    def jobs(self) -> int:
        """Jobs over every condition."""
        return self.configurations() * len(self.shapes) * len(self.seeds) * len(self.conditions)


#: Sized for about 10 minutes on an idle 2-core machine (what it took: docs/mesh.md's front section);
#: the power crust and the view triangulation (screened Poisson, seconds a job: FULL only).
DEFAULT = Grid(
    resolution=(32, 64, 128),
    sfs=("second_order", "perspective", "truth"),
    averaging_s=(0.5, 8.0),
    surface=("power_crust", "view"),
    shapes=("vase", "bowl"),
    seeds=(0, 1, 2),
)
#: Every SFS variant of conf/sfs, three anchorings, three surfaces, all seven held-out shapes, seeds 0–9 (hours).
FULL = Grid(
    resolution=(32, 64, 128),
    sfs=("second_order", "lax_friedrichs", "godunov", "perspective", "oren_nayar", "phong", "truth"),
    averaging_s=(0.5, 2.0, 8.0),
    surface=("power_crust", "view", "poisson"),
    shapes=("plate_edge", "ring", "bowl", "multi", "partial", "off_centre", "vase"),
    seeds=tuple(range(10)),
)


def sweep_overrides(grid: Grid, condition: str) -> list[str]:
    """The ``nirspi-run -m`` overrides of one condition's sweep (its grid as comma lists)."""
    if condition not in CONDITIONS:
        raise ValueError(f"condition {condition!r}; allowed: {sorted(CONDITIONS)}")

    def join(values: Sequence[Any]) -> str:
        return ",".join(str(v) for v in values)

    return [
        *FIXED,
        *CONDITIONS[condition],
        *QUIET,
        f"camera.resolution={join(grid.resolution)}",
        f"sfs={join(grid.sfs)}",
        f"itof.averaging_s={join(grid.averaging_s)}",
        f"surface={join(grid.surface)}",
        f"scene={join(grid.shapes)}",
        f"seed={join(grid.seeds)}",
    ]


def grid_points(grid: Grid) -> list[dict[str, Any]]:
    """Every job of the grid as ``{condition, camera.resolution, sfs, itof.averaging_s, surface,
    scene, seed}`` (the cartesian product the sweeps run)."""
    keys = ("condition", "camera.resolution", "sfs", AVERAGING, "surface", "scene", "seed")
    axes = (grid.conditions, grid.resolution, grid.sfs, grid.averaging_s, grid.surface, grid.shapes, grid.seeds)
    return [dict(zip(keys, combo)) for combo in itertools.product(*axes)]


def front_mask(values: np.ndarray) -> np.ndarray:
    """Non-dominated rows of ``values`` (rows × objectives, every objective minimised): no other
    row is at least as good in each and strictly better in one. Rows with a non-finite value are
    never on the front. The project's :func:`nirspi_pipe.app.objective.pareto_mask`."""
    # start-up: the app layer (hydra) loads only when a front is computed
    from nirspi_pipe.app.objective import pareto_mask

    v = np.asarray(values, dtype=float)
    return pareto_mask(v, ["minimize"] * (v.shape[1] if v.ndim == 2 else 0))


def summarise(frame: Any) -> Any:
    """One row per (condition, resolution, sfs, averaging, surface) of a load_results table with a
    ``condition`` column: jobs, ok jobs; for chamfer and fused depth error the mean over the shapes
    of each shape's median over the seeds (``chamfer_mm``, ``depth_mm``), the smallest and largest
    job (``_min``, ``_max``) and each shape's median (``_by_shape``); the median over the jobs of
    ``timings_ms.total`` (``total_ms``) and of the same less the scene's rendering and the metrics
    (``time_ms``, :data:`NOT_A_CAMERA_COST`); the split by stage and the front flags (:func:`split_and_front`). A
    configuration with a job that failed or lacks a value has no summary (NaN)."""
    # start-up: pandas loads with the table
    import pandas as pd

    keys = ["condition", *(col for col, _ in AXES)]
    # consolidated: load_results' wide frame, built column by column, made every assign below warn
    frame = frame.copy()
    rows = []
    for key, group in frame.groupby(keys, sort=True, dropna=False):
        ok = group[group["status"] == "ok"]
        row: dict[str, Any] = dict(zip(keys, key))
        row["jobs"] = len(group)
        row["ok"] = len(ok)
        row["shapes"] = ",".join(sorted(set(group["scene"].astype(str))))
        cols = [TIME, *NOT_A_CAMERA_COST]
        if all(c in ok.columns for c in cols):
            t = ok[cols].apply(pd.to_numeric, errors="coerce")
            run_ms = t[TIME] - t[list(NOT_A_CAMERA_COST)].sum(axis=1, min_count=len(NOT_A_CAMERA_COST))
        else:
            run_ms = pd.Series([], dtype=float)
        ok = ok.assign(_run_ms=run_ms, _total_ms=pd.to_numeric(ok[TIME], errors="coerce") if TIME in ok else math.nan)
        for col, name in (
            (CHAMFER, "chamfer_mm"),
            (DEPTH, "depth_mm"),
            ("_run_ms", "time_ms"),
            ("_total_ms", "total_ms"),
        ):
            vals = pd.to_numeric(ok[col], errors="coerce") if col in ok.columns else pd.Series([], dtype=float)
            complete = len(ok) == len(group) and len(vals) > 0 and bool(np.isfinite(vals).all())
            if name in ("time_ms", "total_ms"):
                row[name] = float(vals.median()) if complete else math.nan
                continue
            by_shape = vals.groupby(ok["scene"].astype(str)).median() if complete else None
            row[name] = float(by_shape.mean()) if by_shape is not None else math.nan
            row[f"{name}_min"] = float(vals.min()) if complete else math.nan
            row[f"{name}_max"] = float(vals.max()) if complete else math.nan
            row[f"{name}_by_shape"] = (
                ", ".join(f"{k} {v:.2f}" for k, v in by_shape.items()) if by_shape is not None else ""
            )
        rows.append(row)
    table = pd.DataFrame(rows)
    return split_and_front(table)


def split_and_front(table: Any) -> Any:
    """Add the error split by stage (each row against the ``sfs=truth`` row of its condition,
    resolution, averaging and surface) and the front flags (per condition)."""
    out = table.copy()
    pair = ["condition", "camera.resolution", AVERAGING, "surface"]
    truth = out[out["sfs"] == "truth"].set_index(pair)
    for stat in ("chamfer_mm", "depth_mm"):
        ref = [
            truth[stat].get(tuple(r[k] for k in pair), math.nan) if len(truth) else math.nan for _, r in out.iterrows()
        ]
        out[f"truth_{stat}"] = ref
        out[f"sfs_share_{stat}"] = out[stat] - out[f"truth_{stat}"]
    # anchoring and fusion: the fused depth error with the exact depth; surface: what the chamfer
    # with the exact depth adds to (or takes from) that depth error
    out["anchoring_mm"] = out["truth_depth_mm"]
    out["surface_mm"] = out["truth_chamfer_mm"] - out["truth_depth_mm"]
    out["front_chamfer"] = False
    out["front_depth"] = False
    # the oracle is a reference, not something a camera can run: never on a front
    real = out[out["sfs"] != "truth"]
    for _cond, idx in real.groupby("condition").groups.items():
        sub = out.loc[idx]
        for stat, flag in (("chamfer_mm", "front_chamfer"), ("depth_mm", "front_depth")):
            values = sub[[stat, "time_ms", AVERAGING]].to_numpy(dtype=float)
            out.loc[idx, flag] = front_mask(values)
    return out


def _fmt(x: float, digits: int = 2) -> str:
    return "—" if not math.isfinite(x) else f"{x:.{digits}f}"


def _cell(r: Any, stat: str) -> str:
    """``mean (shape median, …; smallest–largest job)`` of one configuration's ``stat``."""
    if not math.isfinite(r[stat]):
        return "—"
    shapes = str(r[f"{stat}_by_shape"])
    return f"{r[stat]:.2f} ({shapes}; {r[f'{stat}_min']:.2f}–{r[f'{stat}_max']:.2f})"


LEGEND = (
    "Per configuration: `time` the median over its jobs of `timings_ms.total` less `timings_ms.scene` and "
    "`timings_ms.metrics` (the simulator's rendering and the scoring: no camera runs them), ms (`total`: "
    "the median `timings_ms.total`); chamfer and fused depth: "
    "the mean over the shapes of each shape's median over the seeds (each shape's median; the smallest–largest "
    "job). front: C on the chamfer front, D on the depth front (error, time and iToF averaging time; the "
    "`sfs=truth` oracle rows are references, never on a front). Split "
    "by stage against the `sfs=truth` row of the same resolution, averaging and surface: SFS share = this "
    "row − the truth row; anchoring = the truth row's fused depth error; surface = the truth row's chamfer "
    "− its fused depth error (negative: the mesh lies closer to the truth than the fused points' z-error)."
)


def markdown(table: Any, front_only: bool = False) -> str:
    """One Markdown table per condition, rows by time; front members marked (``front_only``: the
    front members and the oracle rows only)."""
    parts = [LEGEND, ""]
    if front_only:
        table = table[table["front_chamfer"] | table["front_depth"] | (table["sfs"] == "truth")]
    for cond in [c for c in CONDITIONS if c in set(table["condition"])]:
        sub = table[table["condition"] == cond]
        parts.append(f"**{cond}** ({' '.join(CONDITIONS[str(cond)])})\n")
        parts.append(
            "| res | sfs | iToF avg (s) | surface | ok/jobs | time (ms) | total (ms) | chamfer (mm) "
            "| fused depth (mm) "
            "| front | SFS share chamfer / depth | anchoring | surface |"
        )
        parts.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for _, r in sub.sort_values(["time_ms", "chamfer_mm"]).iterrows():
            marks = "/".join(m for m, f in (("C", r["front_chamfer"]), ("D", r["front_depth"])) if f) or ""
            share = (
                "(oracle)"
                if r["sfs"] == "truth"
                else f"{_fmt(r['sfs_share_chamfer_mm'])} / {_fmt(r['sfs_share_depth_mm'])}"
            )
            parts.append(
                f"| {int(r['camera.resolution'])} | {r['sfs']} | {r[AVERAGING]:g} | {r['surface']} "
                f"| {int(r['ok'])}/{int(r['jobs'])} | {_fmt(r['time_ms'], 0)} | {_fmt(r['total_ms'], 0)} "
                f"| {_cell(r, 'chamfer_mm')} | {_cell(r, 'depth_mm')} | {marks} "
                f"| {share} | {_fmt(r['anchoring_mm'])} | {_fmt(r['surface_mm'])} |"
            )
        parts.append("")
    return "\n".join(parts)


def figure(table: Any, path: Path) -> None:
    """Error against time, one panel per (condition, metric): colour the SFS variant (grey: the
    ``sfs=truth`` oracle), marker the surface, filled the shortest iToF averaging and hollow the
    longer ones; front members ringed and labelled with their resolution and surface."""
    # start-up: matplotlib loads only for the figure
    import matplotlib

    matplotlib.use("Agg")
    # start-up: matplotlib loads only for the figure
    import matplotlib.pyplot as plt

    # start-up: matplotlib loads only for the figure
    import matplotlib.ticker

    # start-up: matplotlib loads only for the figure
    from matplotlib.lines import Line2D

    conds = [c for c in CONDITIONS if c in set(table["condition"])]
    fig, axes = plt.subplots(len(conds), 2, figsize=(11, 3.8 * len(conds)), squeeze=False)
    variants = [v for v in sorted(set(table["sfs"])) if v != "truth"]
    colours = {v: f"C{k}" for k, v in enumerate(variants)} | {"truth": "0.45"}
    markers = {s: m for s, m in zip(sorted(set(table["surface"])), "osD^v<>ph")}
    shortest = float(table[AVERAGING].min())
    handles = [Line2D([], [], ls="none", marker="o", color=colours[v], label=v) for v in variants]
    handles.append(Line2D([], [], ls="none", marker="o", color=colours["truth"], label="truth (oracle)"))
    handles += [Line2D([], [], ls="none", marker=m, color="k", mfc="none", label=s) for s, m in markers.items()]
    handles.append(Line2D([], [], ls="none", marker="o", ms=10, mfc="none", color="C3", label="on the front"))
    for i, cond in enumerate(conds):
        sub = table[table["condition"] == cond]
        for j, (stat, flag, label) in enumerate(
            (("chamfer_mm", "front_chamfer", "chamfer (mm)"), ("depth_mm", "front_depth", "fused depth RMSE (mm)"))
        ):
            ax = axes[i][j]
            for (sfs, surface, avg), part in sub.groupby(["sfs", "surface", AVERAGING]):
                colour = colours[str(sfs)]
                ax.scatter(
                    part["time_ms"],
                    part[stat],
                    marker=markers[str(surface)],
                    facecolors=colour if float(avg) <= shortest else "none",
                    edgecolors=colour,
                    s=24,
                )
            front = sub[sub[flag]]
            ax.scatter(front["time_ms"], front[stat], s=90, facecolors="none", edgecolors="C3")
            for _, r in front.iterrows():  # which resolution and surface each member is
                ax.annotate(
                    f"{int(r['camera.resolution'])}² {str(r['surface']).replace('power_crust', 'crust')}",
                    (r["time_ms"], r[stat]),
                    fontsize=6,
                    xytext=(4, 4),
                    textcoords="offset points",
                )
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # minor labels overlapped
            ax.set_xlabel("median time, timings_ms.total − scene − metrics (ms)")
            ax.set_ylabel(label)
            ax.set_title(
                f"{cond}: mean of the shapes' medians; filled iToF avg {shortest:g} s, hollow longer",
                fontsize=9,
            )
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(handles=handles, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def seeds_of(text: str) -> tuple[int, ...]:
    """``0-4`` or ``0,3,7`` as seeds."""
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-", 1))
        return tuple(range(lo, hi + 1))
    return tuple(int(v) for v in text.split(","))


def run_sweep(out: Path, condition: str, grid: Grid, extra: Sequence[str]) -> int:
    """One condition's ``nirspi-run -m`` sweep into ``out/condition``; its exit status."""
    exe = shutil.which("nirspi-run") or "nirspi-run"
    cmd = [exe, "-m", *sweep_overrides(grid, condition), *extra, f"hydra.sweep.dir={out / condition}"]
    print(f"front: {condition}: {grid.jobs() // len(grid.conditions)} jobs -> {out / condition}", flush=True)
    return subprocess.call(cmd, env=dict(os.environ))


def collect(out: Path, conditions: Sequence[str]) -> Any:
    """The sweeps' records, read back with :func:`nirspi_pipe.load_results`, with ``condition``."""
    # start-up: pandas and the results loader load after the sweeps
    import pandas as pd

    # start-up: pandas and the results loader load after the sweeps
    import nirspi_pipe

    frames = []
    for cond in conditions:
        folder = out / cond
        if not folder.is_dir():
            continue
        f = nirspi_pipe.load_results(folder, refresh=True)
        f["condition"] = cond
        frames.append(f)
    if not frames:
        raise SystemExit(f"front: no sweep folder under {out}")
    frame = pd.concat(frames, ignore_index=True)
    frame[AVERAGING] = pd.to_numeric(frame[AVERAGING])
    frame["camera.resolution"] = pd.to_numeric(frame["camera.resolution"]).astype(int)
    return frame


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="folder of the sweeps and the tables")
    ap.add_argument("--full", action="store_true", help="the full grid (hours)")
    ap.add_argument("--shapes", help="comma list of held-out shapes (default: the grid's)")
    ap.add_argument("--seeds", help="0-2 or 0,3,7 (default: the grid's)")
    ap.add_argument("--conditions", help=f"comma list of {','.join(CONDITIONS)} (default: both)")
    ap.add_argument("--tables-only", action="store_true", help="read the records of an earlier run; run nothing")
    args, extra = ap.parse_known_args(argv)
    grid = FULL if args.full else DEFAULT
    try:
        grid = Grid(
            resolution=grid.resolution,
            sfs=grid.sfs,
            averaging_s=grid.averaging_s,
            surface=grid.surface,
            shapes=tuple(args.shapes.split(",")) if args.shapes else grid.shapes,
            seeds=seeds_of(args.seeds) if args.seeds else grid.seeds,
            conditions=tuple(args.conditions.split(",")) if args.conditions else grid.conditions,
        )
    except ValueError as exc:
        print(f"front: {exc}", file=sys.stderr)
        return 2
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    status = 0
    if not args.tables_only:
        print(f"front: {grid.jobs()} jobs ({grid.configurations()} configurations per condition)", flush=True)
        for cond in grid.conditions:
            status = max(status, run_sweep(out, cond, grid, extra))
    frame = collect(out, grid.conditions)
    table = summarise(frame)
    table.to_parquet(out / "front.parquet", index=False)
    table.to_csv(out / "front.csv", index=False)
    (out / "front.md").write_text(markdown(table))
    (out / "front_members.md").write_text(markdown(table, front_only=True))
    figure(table, out / "front.png")
    bad = int((frame["status"] != "ok").sum())
    print(
        f"front: {len(frame)} jobs read back ({bad} not ok) in {time.monotonic() - start:.0f} s -> "
        f"{out / 'front.md'}, front.csv, front.parquet, front.png",
        flush=True,
    )
    return status


if __name__ == "__main__":
    sys.exit(main())
