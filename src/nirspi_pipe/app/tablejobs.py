"""A sweep's paper tables, built side by side: each experiment's tables in a forked process.

A sweep that ran several experiments (``+experiment=paper``: Table 2, Tables 3/5/6/7, Table 4 and
Figure 9) builds each experiment's tables from that experiment's rows only, so the experiments'
builds are independent. Built one after another they kept one core busy and the others idle for
about 15 s at the end of the paper sweep (2-core machine, ``nirspi-bench paper --experiment
paper``); here each experiment's build runs in a forked child, at most one per core, and the
parent prints each build's lines in the experiments' order once it is done.

The files are the same bytes either way (``tests/test_tablejobs.py``). A child that dies (a
segfault in a plotting library, the out-of-memory killer) costs only its own experiment's tables:
the parent says so in one line and builds that experiment's tables itself, one after another.
Where ``os.fork`` does not exist, or there is one experiment or one core, everything is built
in this process.
"""

from __future__ import annotations

import contextlib
import io
import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pandas as pd

__all__ = ["build_parts"]

#: ``build(frame, sweep, names) -> built names``: one experiment's tables (``results.build_tables``).
Build = Callable[[pd.DataFrame, Path, list[str]], list[str]]

# what a forked child builds: set in the parent just before the pool forks, read by index in the
# child (the frames are inherited, never pickled)
_PARTS: list[tuple[pd.DataFrame, list[str]]] = []
_BUILD: list[Build] = []


def _cost(part: tuple[pd.DataFrame, list[str]]) -> int:
    """A part's expected build time, for the order of submission: rows × tables."""
    frame, names = part
    return len(frame) * max(1, len(names))


def _child(index: int, sweep: str) -> tuple[list[str], str]:
    """In a forked child: build part ``index``; ``(built names, what it printed)``."""
    frame, names = _PARTS[index]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        built = _BUILD[0](frame, Path(sweep), names)
    return built, out.getvalue()


def build_parts(
    parts: Sequence[tuple[pd.DataFrame, list[str]]], sweep: Path, build: Build, workers: int | None = None
) -> list[str]:
    """``build(frame, sweep, names)`` of every part ``(frame, names)``, in forked children (at most
    ``workers`` at once, default one per core) when there are two parts or more; their printed
    lines in the parts' order. Returns the built names in the parts' order."""
    parts = list(parts)
    workers = min(len(parts), workers or os.cpu_count() or 1)
    if workers < 2 or not hasattr(os, "fork"):
        return [name for frame, names in parts for name in build(frame, sweep, names)]
    _PARTS[:] = parts
    _BUILD[:] = [build]
    results: dict[int, tuple[list[str], str]] = {}
    order = sorted(range(len(parts)), key=lambda i: -_cost(parts[i]))
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            futures = {i: pool.submit(_child, i, str(sweep)) for i in order}
            for i, fut in futures.items():
                try:
                    results[i] = fut.result()
                except (BrokenProcessPool, Exception):  # noqa: BLE001 - built below, in this process
                    pass
    finally:
        _PARTS.clear()
        _BUILD.clear()
    built: list[str] = []
    for i, (frame, names) in enumerate(parts):
        if i in results:
            names_built, printed = results[i]
            sys.stdout.write(printed)
            built += names_built
        else:
            print(
                f"nirspi-run: tables {', '.join(names)} were not built side by side (a table process died);"
                " building them here",
                file=sys.stderr,
                flush=True,
            )
            built += build(frame, sweep, names)
    sys.stdout.flush()
    return built
