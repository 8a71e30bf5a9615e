"""``report.md``: every regenerated table of a sweep beside the paper's, and its figures."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import pandas as pd

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
        sha = frame["git_sha"].dropna().unique().tolist() if "git_sha" in frame else []
        lines.append(f"{len(frame)} jobs ({', '.join(f'{v} {k}' for k, v in status.items())}); "
                     f"code {', '.join(s[:10] for s in sha) or 'unknown'}.")
        if "timings_ms.total" in frame:
            lines.append(f"Pipeline time summed over jobs: {frame['timings_ms.total'].sum() / 1e3:.1f} s.")
    for name in tables:
        lines += ["", f"## {name}", ""]
        md = out / f"{name}.md"
        lines.append(md.read_text().strip() if md.is_file() else f"_{name}.md was not written_")
        for png in sorted(out.glob(f"{name}*.png")):
            lines += ["", f"![{png.stem}](tables/{png.name})"]
    path = sweep / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
