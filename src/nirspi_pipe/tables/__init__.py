"""Paper-shaped tables built from a sweep's results.

An experiment config lists the tables it feeds under the top-level key ``tables`` (for example
``tables: [table2]``). After the sweep, :class:`nirspi_pipe.app.results.CollectResults` calls
``nirspi_pipe.tables.<name>.build(frame, out_dir)`` for each, where ``frame`` is the sweep's
results table and ``out_dir`` is ``<sweep>/tables``. A builder writes ``<name>.csv`` and
``<name>.md`` (and figures) there and returns the table as a DataFrame. ``nirspi-collect DIR
--tables table2`` rebuilds them from the records.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import pandas as pd

__all__ = ["build_table"]


def build_table(name: str, frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build table ``name`` from a results frame into ``out_dir`` (created if needed)."""
    if not name.isidentifier():
        raise ValueError(f"table name must be an identifier, got {name!r}")
    try:
        module = importlib.import_module(f"nirspi_pipe.tables.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"nirspi_pipe.tables.{name}":
            raise ValueError(f"unknown table {name!r}: no module nirspi_pipe.tables.{name}") from None
        raise
    out_dir.mkdir(parents=True, exist_ok=True)
    return module.build(frame, out_dir)
