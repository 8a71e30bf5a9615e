"""Table 4: mesh quality (equiangle skewness) of the SFS mesh and of the final mesh (iToF mapping +
heat filter + power crust), per scan method, without fog. Table 5 is the same with fog
(:mod:`nirspi_pipe.tables.table5` calls :func:`build_skewness`).

* ``skewness_sfs``: ``metrics.skewness_sfs_mean``, the mean equiangle skewness
  ``max((θmax − 60°)/120°, (60° − θmin)/60°)`` of the pixel-grid mesh of the metric SFS depth;
* ``skewness_mesh_itof``: ``metrics.skewness_mean``, the same for the final power-crust mesh.

Rows: one per scan method, mean ± std (min, max) over objects × seeds × kLux levels, the standard
error clustered by seed (:mod:`nirspi_pipe.stats`), the paper's values, the difference (ours −
paper) and the paired difference to *Basic*. Rankings: ``<name>_rankings.csv`` (Holm, both seed
halves). Jobs run with ``surface.remesh_iterations=0`` (the paper has no isotropic remeshing; a
departure, docs/paper.md) are kept apart: their final-mesh skewness is the ``mesh_noremesh``
column (``<name>_noremesh.csv``), never pooled with the remeshed jobs. Writes ``<name>.csv``,
``<name>.md`` and ``<name>.png``. From ``nirspi-run -m +experiment=table4``.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from nirspi_pipe.tables import _common as common
from nirspi_pipe.tables.table3 import fogged

__all__ = ["build", "build_skewness"]

COLUMNS = {"skewness_sfs": "metrics.skewness_sfs_mean", "skewness_mesh_itof": "metrics.skewness_mean"}
REMESH = "surface.remesh_iterations"


def _split_remesh(df: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The remeshed jobs (the default) and those run with ``surface.remesh_iterations=0``."""
    if REMESH not in df.columns:
        return df, df.iloc[0:0]
    none = pd.to_numeric(df[REMESH], errors="coerce") == 0
    return df[~none], df[none]


def build_skewness(frame: pd.DataFrame, out_dir: Path, name: str, fog: bool) -> pd.DataFrame:
    """Skewness table ``name`` (table4: ``fog=False``, table5: ``fog=True``) into ``out_dir``."""
    out_dir = Path(out_dir)
    df = common.ok_rows(frame, list(COLUMNS.values()), name)
    df = df[fogged(df) == fog]
    if df.empty:
        raise ValueError(f"{name} needs {'fogged' if fog else 'fog-free'} jobs: run `nirspi-run -m +experiment={name}`")
    df, plain = _split_remesh(df)
    if df.empty:
        raise ValueError(f"{name} needs jobs with the default remeshing: run `nirspi-run -m +experiment={name}`")
    paper = common.paper_reference(name).set_index("scan")
    table = pd.DataFrame([common.compared_row(df, scan, g, COLUMNS, paper) for scan, g in common.scan_groups(df)])
    common.write_csv(table, out_dir / f"{name}.csv")
    claims = common.column_rankings(df, COLUMNS, lambda key: False)  # lower skewness is better
    common.write_csv(claims, out_dir / f"{name}_rankings.csv")
    noremesh = _noremesh(plain)
    if len(noremesh):
        common.write_csv(noremesh, out_dir / f"{name}_noremesh.csv")
    (out_dir / f"{name}.md").write_text(
        common.with_families(_markdown(table, frame, pd.concat([df, plain]), name, fog, claims, noremesh), claims)
    )
    t = table.set_index("scan").reindex(list(common.SCANS))
    bar = common.bar_figure(
        f"Table {name[len('table') :]}: equiangle skewness, {'fog' if fog else 'no fog'}",
        [common.SCAN_LABELS[s] for s in common.SCANS],
        {k: (t[f"{k}_mean"].tolist(), t[f"{k}_std"].tolist()) for k in COLUMNS},
        {k: t[f"paper_{k}"].tolist() for k in COLUMNS},
        "mean equiangle skewness (0 best, 1 degenerate)",
        f"Error bars: ± 1 standard deviation of the jobs' mean skewness ({common.count_range(t['n'])} "
        "jobs per scan: objects × kLux × seeds), the spread between jobs, not the uncertainty of the mean "
        f"({name}.md gives the standard errors clustered by seed).",
    )
    common.save_figure(out_dir / f"{name}.png", bar)
    return table


def _noremesh(plain: pd.DataFrame) -> pd.DataFrame:
    """Per scan: both skewness columns of the jobs without remeshing (mean, clustered SE, n)."""
    rows = []
    for scan, g in common.scan_groups(plain):
        row: dict = {"scan": scan, "n": int(len(g))}
        for key, col in COLUMNS.items():
            row[f"{key}_mean"] = float(g[col].mean())
            row.update(common.cell(g, col, key))
        rows.append(row)
    return pd.DataFrame(rows)


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 4 (no fog) from a results frame into ``out_dir``."""
    return build_skewness(frame, out_dir, "table4", fog=False)


def _markdown(
    table: pd.DataFrame,
    frame: pd.DataFrame,
    df: pd.DataFrame,
    name: str,
    fog: bool,
    claims: pd.DataFrame,
    noremesh: pd.DataFrame,
) -> str:
    title = "with 3 µm fog" if fog else "without fog"
    nr = noremesh.set_index("scan") if len(noremesh) else None
    head = "| Scanning method | Skewness SFS | Skewness mesh+iToF | n |"
    rule = "|---|---:|---:|---:|"
    if nr is not None:
        head = "| Scanning method | Skewness SFS | Skewness mesh+iToF | mesh+iToF, no remeshing | n (no remeshing) |"
        rule = "|---|---:|---:|---:|---:|"
    lines = [
        f"# Table {name[len('table') :]}: surface quality (mean equiangle skewness), {title}",
        "",
        "Each cell: ours, mean ± standard error clustered by seed over objects × seeds × kLux (the paper's "
        "value). ANSYS bands: < 0.25 excellent, < 0.5 good, < 0.75 fair, < 0.9 poor. Our final mesh is "
        "isotropically remeshed (`surface.remesh_iterations`, a departure from the paper)"
        + (
            "; the last column is the same mesh without remeshing (`surface.remesh_iterations=0`)."
            if nr is not None
            else "."
        ),
        "",
        head,
        rule,
    ]
    for r in table.itertuples():
        cells = [
            f"{common.fmt(getattr(r, f'{k}_mean'), getattr(r, f'{k}_se'), 3)} ({getattr(r, f'paper_{k}'):.2f})"
            for k in COLUMNS
        ]
        if nr is not None and r.scan in nr.index:
            o = nr.loc[r.scan]
            cells.append(common.fmt(o["skewness_mesh_itof_mean"], o["skewness_mesh_itof_se"], 3))
            cells.append(f"{r.n} ({int(o['n'])})")
        else:
            cells.append(str(r.n))
        lines.append(f"| {common.SCAN_LABELS[r.scan]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Rankings (lower skewness better; only where the paired difference holds after Holm's correction "
        f"over the six pairs in both seed halves): {common.column_notes(claims)}.",
        "",
        f"Ranges over all jobs: SFS {table['skewness_sfs_min'].min():.2f}–{table['skewness_sfs_max'].max():.2f}, "
        f"mesh+iToF {table['skewness_mesh_itof_min'].min():.2f}–{table['skewness_mesh_itof_max'].max():.2f}. "
        f"Mean change SFS → mesh+iToF: {(table['skewness_mesh_itof_mean'] - table['skewness_sfs_mean']).mean():+.2f} "
        f"(paper: {(table['paper_skewness_mesh_itof'] - table['paper_skewness_sfs']).mean():+.2f}).",
        "",
        common.rows_note(df, frame[fogged(frame) == fog]),
    ]
    return "\n".join(lines) + "\n"
