"""``sweep.json``, the file the ``nirspi`` sweeper writes in a sweep folder (start time, totals,
every job's key and overrides, each job's fate), read back checked (:func:`load_sweep_file`), and
the progress it gives: :func:`progress_line` from it and the records written since the sweep
started, printed by a :class:`ProgressWatcher` as records appear. :func:`nirspi_pipe.app.results.collect`
uses it to list jobs that never wrote a record.
"""

from __future__ import annotations

import json
import math
import re
import threading
import time
from pathlib import Path
from typing import Any

from nirspi_pipe.records import RECORD_NAME, RECORD_READ_LIMIT, read_record
from nirspi_pipe.safeio import read_regular

__all__ = [
    "SWEEP_FILE",
    "ProgressWatcher",
    "SweepFileError",
    "format_progress",
    "load_sweep_file",
    "progress_line",
    "read_sweep_file",
    "record_status",
]

SWEEP_FILE = "sweep.json"
_KEY = re.compile(r"^[0-9a-f]{16}$")


class SweepFileError(ValueError):
    """``sweep.json`` exists but is not what the sweeper writes; the message names the file."""


def load_sweep_file(sweep_dir: Path) -> dict[str, Any] | None:
    """``sweep.json`` of a sweep folder, checked; None when there is none (e.g. a basic sweep).

    Raises :class:`SweepFileError` (one line naming the file) when it is unreadable, not JSON, or
    lacks a ``jobs`` list of ``{"key": <16 hex digits>, ...}`` (a key is never a path)."""
    path = Path(sweep_dir) / SWEEP_FILE
    if not path.exists():
        return None
    try:  # a regular file only (a FIFO would block), bounded like a record
        info = json.loads(read_regular(path, RECORD_READ_LIMIT, str(path)))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise SweepFileError(
            f"{path} is not readable JSON ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    problem = None
    if not isinstance(info, dict):
        problem = f"expected a JSON object, got {type(info).__name__}"
    elif not isinstance(info.get("jobs"), list):
        problem = "expected a 'jobs' list"
    else:
        for i, job in enumerate(info["jobs"]):
            if not isinstance(job, dict) or not isinstance(job.get("key"), str) or not _KEY.match(job["key"]):
                problem = f"jobs[{i}] needs a 'key' of 16 hex digits"
                break
    if problem is None:
        for name in ("started", "to_run"):
            if name in info and not isinstance(info[name], (int, float)):
                problem = f"'{name}' must be a number"
    if problem:
        raise SweepFileError(
            f"{path} is malformed: {problem} (it is written by `nirspi-run -m`; "
            "delete it to collect every record.json below the folder)"
        )
    return info


def read_sweep_file(sweep_dir: Path) -> dict[str, Any] | None:
    """``sweep.json`` of a sweep folder, or None when there is none or it is malformed."""
    try:
        return load_sweep_file(sweep_dir)
    except SweepFileError:
        return None


def record_status(folder: Path) -> str | None:
    try:
        return read_record(folder / RECORD_NAME).get("meta", {}).get("status")
    except (OSError, ValueError, AttributeError):
        return None


def progress_line(sweep_dir: Path) -> str | None:
    """``"7/12 jobs done (1 failed), 3 skipped | elapsed 0:42 | ETA 1:12"`` for a running sweep,
    from ``sweep.json`` and the records written since the sweep started; None without one."""
    info = read_sweep_file(sweep_dir)
    if not info:
        return None
    started = float(info.get("started", 0.0))
    done = failed = 0
    for job in info["jobs"]:
        if job.get("skipped") or job.get("duplicate") or not job.get("launched", True):
            continue
        rec = Path(sweep_dir) / job["key"] / RECORD_NAME
        try:
            if rec.stat().st_mtime >= started:
                done += 1
                failed += record_status(rec.parent) != "ok"
        except OSError:
            continue
    total = int(info.get("to_run", len(info["jobs"])))
    skipped = sum(bool(j.get("skipped")) and not j.get("duplicate") for j in info["jobs"])
    not_run = sum(bool(j.get("gave_up") or j.get("uncomposable") or j.get("refused")) for j in info["jobs"])
    return format_progress(done, failed, total, skipped, not_run, max(0.0, time.time() - started))


def format_progress(done: int, failed: int, total: int, skipped: int, not_run: int, elapsed_s: float) -> str:
    """The progress line: ``"7/12 jobs done (1 failed), 3 skipped | elapsed 0:42 | ETA 1:12"``."""
    eta = elapsed_s / done * (total - done) if done else float("nan")

    def hms(s: float) -> str:
        if math.isnan(s):
            return "?"
        s = round(s)
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"

    head = f"{done}/{total} jobs done" + (f" ({failed} failed)" if failed else "")
    if skipped:
        head += f", {skipped} skipped"
    if not_run:
        head += f", {not_run} not run (failed)"
    return " | ".join([head, f"elapsed {hms(elapsed_s)}", f"ETA {hms(eta)}"])


class ProgressWatcher(threading.Thread):
    """Prints :func:`progress_line` whenever another job of the sweep finishes.

    It runs in the process that launched the sweep and watches the records appear in the sweep
    folder, so progress shows on the terminal whatever the launcher (joblib workers, submitit
    subprocesses, SLURM nodes on a shared file system).
    """

    def __init__(self, sweep_dir: Path, interval_s: float = 2.0) -> None:
        super().__init__(name="nirspi-progress", daemon=True)
        self.sweep_dir, self.interval_s = Path(sweep_dir), interval_s
        self._halt = threading.Event()
        self._last: str | None = None

    def run(self) -> None:
        while not self._halt.wait(self.interval_s):
            self.report()

    def report(self) -> None:
        """Print the progress line if the count of finished jobs changed since the last one."""
        line = progress_line(self.sweep_dir)
        head = line.split(" | ", 1)[0] if line else None
        if line and head != self._last:
            self._last = head
            print(f"nirspi-run: {line}", flush=True)

    def stop(self) -> None:
        """Stop watching and print the final state."""
        self._halt.set()
        if self.is_alive():
            self.join()
