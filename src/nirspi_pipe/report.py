"""``report.md``: every regenerated table of a sweep beside the paper's, and its figures."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import pandas as pd

from nirspi_pipe.outputfiles import atomic_write

__all__ = ["write_report"]


def write_report(sweep: Path, tables: list[str], frame: pd.DataFrame) -> Path:
    """Write ``<sweep>/report.md`` from the tables' Markdown files and PNG figures in
    ``<sweep>/tables``. Returns the report's path."""
    out = sweep / "tables"
    lines = [
        "# nirspi-pipe: regenerated results",
        "",
        f"Sweep `{sweep}`, collected {_dt.datetime.now(_dt.timezone.utc):%Y-%m-%d %H:%M} UTC.",
    ]
    if len(frame):
        status = frame["status"].value_counts().to_dict()
        code = frame["code"].dropna().unique().tolist() if "code" in frame else []
        if not code and "git_sha" in frame:  # records written before the code label existed
            code = [f"git:{s[:12]}" for s in frame["git_sha"].dropna().unique()]
        lines.append(
            f"{len(frame)} jobs ({', '.join(f'{v} {k}' for k, v in status.items())}); "
            f"code {', '.join(sorted(code)) or 'unknown'}."
        )
        flags = [
            c
            for c in frame.columns
            if c.startswith("metrics.") and c.endswith(("degenerate_reference", "degenerate_image"))
        ]
        hit = frame[flags].apply(pd.to_numeric, errors="coerce").fillna(0.0).gt(0.0)
        if flags and hit.to_numpy().any():
            lines.append(
                f"{int(hit.any(axis=1).sum())} jobs left a normalised score out as degenerate (docs/paper.md, "
                '"Metrics"; per flag: '
                + ", ".join(f"{c.removeprefix('metrics.')} {int(hit[c].sum())}" for c in flags if hit[c].any())
                + "); the tables say where."
            )
        if "timings_ms.total" in frame:
            lines.append(f"Pipeline time summed over jobs: {frame['timings_ms.total'].sum() / 1e3:.1f} s.")
    for name in tables:
        lines += ["", f"## {name}", ""]
        md = out / f"{name}.md"
        lines.append(md.read_text().strip() if md.is_file() else f"_{name}.md was not written_")
        for png in sorted(out.glob(f"{name}*.png")):
            lines += ["", f"![{png.stem}](tables/{png.name})"]
    return atomic_write(sweep / "report.md", "\n".join(lines) + "\n")
