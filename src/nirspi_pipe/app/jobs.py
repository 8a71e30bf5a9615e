"""One sweep job, crash-isolated: locked, counted, and run in a child process.

Whatever the launcher (joblib workers, ``submitit_local`` subprocesses, SLURM tasks), the task
function of a sweep calls :func:`run_sweep_job`, which

1. takes the job folder's lock (:class:`nirspi_pipe.outputfiles.JobLock`), waiting if another sweep
   writing into the same folder is running this very job; if another process completed it
   meanwhile (an ``ok`` record; with ``resume=false`` one newer than this sweep's ``sweep.json``),
   it is not run again, so two identical sweeps into one folder share the work;
2. counts the attempt in ``attempts.json`` (the sweeper stops relaunching a job after
   ``hydra.sweeper.max_attempts`` attempts with the same code, so a deterministic crasher never
   blocks a sweep);
3. runs the job in a forked child process. A child that segfaults, is killed (``SIGKILL`` from
   the kernel's out-of-memory killer or a scheduler) or calls ``os._exit`` takes only itself
   down: the worker writes a ``failed`` record naming the signal or exit code, and the launcher's
   worker, and with it every other job of the sweep, goes on.

Where ``os.fork`` does not exist (Windows) the job runs in-process, without crash isolation.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import logging
import os
import signal
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from nirspi_pipe import execute
from nirspi_pipe.app.configs import scan_indices
from nirspi_pipe.instantiate import plain_config
from nirspi_pipe.outputfiles import JobLock, OutputError, atomic_write
from nirspi_pipe.provenance import code_identity, provenance
from nirspi_pipe.records import RECORD_NAME, new_record, read_record, write_record
from nirspi_pipe.safeio import read_regular
from nirspi_pipe.strictjson import dumps_strict

__all__ = [
    "ATTEMPTS_NAME",
    "CHILD_FAILED_STATUS",
    "OUTPUT_FAILED_STATUS",
    "ClaimedJob",
    "SweepJob",
    "crash_message",
    "execute_attempt",
    "execute_job",
    "read_attempts",
    "run_sweep_job",
]

log = logging.getLogger(__name__)


#: The runner's :func:`nirspi_pipe.execute.execute_job` (the only one) with the config layer's
#: resolver of the scan option a recording names bound (:func:`nirspi_pipe.app.configs.scan_indices`):
#: what every front end (the command line, the launchers, the Python API) runs a job with.
execute_job = functools.partial(execute.execute_job, scan_indices=scan_indices)


ATTEMPTS_NAME = "attempts.json"
_CHILD_FAILED = 70  # exit code of a child whose job runner itself raised (EX_SOFTWARE)
_OUTPUT_FAILED = 74  # exit code of a child that could not write its outputs (EX_IOERR, sysexits.h)

#: Jobs of this process's sweep that failed without a record (:func:`unwritten_failure`): the
#: results callback counts them when no row of ``results.parquet`` shows them.
unwritten_jobs: list[tuple[Path, str]] = []


def read_attempts(folder: Path) -> dict[str, Any]:
    """``attempts.json`` of a job folder: ``{"attempts": n, "source_hash": ..., "last": ...}``;
    ``{"attempts": 0}`` when there is none or it is unreadable."""
    try:
        data = json.loads(read_regular(Path(folder) / ATTEMPTS_NAME, 1 << 16))  # never a FIFO; a few bytes
        if isinstance(data, dict) and isinstance(data.get("attempts"), int):
            return data
    except (OSError, ValueError, RecursionError):
        pass
    return {"attempts": 0}


def attempts_with_this_code(folder: Path) -> int:
    """Attempts made on a job with the code now running (a code change resets the count)."""
    data = read_attempts(folder)
    return int(data["attempts"]) if data.get("source_hash") == code_identity()["source_hash"] else 0


def _bump_attempts(folder: Path) -> int:
    """Count one more attempt at the job in ``folder``. Written atomically but not flushed to disk
    (``durable=False``): a power cut that loses the file reads as 0 attempts, one more try of the
    job at worst, while the flush cost 12 ms a job in the sweeping process, which claims the jobs
    one after another (m1's profile of paper_ci, issue 42 item 6)."""
    n = attempts_with_this_code(folder) + 1
    atomic_write(
        Path(folder) / ATTEMPTS_NAME,
        dumps_strict(
            {
                "attempts": n,
                "source_hash": code_identity()["source_hash"],
                "last": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "pid": os.getpid(),
            }
        ),
        durable=False,
    )
    return n


def crash_message(status: int) -> tuple[str, dict[str, Any]]:
    """The one-line error and record fields for a child's ``waitpid`` status."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = f"signal {sig}"
        hints: dict[int, str] = {
            int(signal.SIGKILL): " (killed: out of memory, or by a scheduler or a user)",
            int(signal.SIGSEGV): " (a crash in native code)",
            int(signal.SIGABRT): " (aborted in native code)",
        }
        hint = hints.get(sig, "")
        return f"job process killed by {name} ({sig}){hint}", {"signal": sig, "exit_code": -sig}
    code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else status
    if code == _OUTPUT_FAILED:
        return (
            "job could not write its record (disk full or unwritable folder; the file is named in the error above)",
            {"exit_code": code, "signal": None},
        )
    return (f"job process exited with code {code} before writing its record", {"exit_code": code, "signal": None})


def deadline_message(timeout_s: float) -> str:
    """The error of a job killed at its deadline (``hydra.launcher.timeout_s``)."""
    return f"job killed after its deadline of {timeout_s:g} s (hydra.launcher.timeout_s)"


def unwritten_failure(out_dir: Path, overrides: list[str], job_num: int | None, exc: OutputError) -> dict[str, Any]:
    """The record of a job that could not even be started because its folder cannot be written
    (disk full, a symbolic link): returned (the caller logs its error), not written."""
    unwritten_jobs.append((Path(out_dir), str(exc)))
    meta = {"status": "failed", "error": str(exc), "error_type": "OutputError", "overrides": overrides}
    return {"meta": {**meta, "job_num": job_num, "job_key": Path(out_dir).name}}


def _done_ok(folder: Path, sweep_file: Path | None, resume: bool) -> dict[str, Any] | None:
    """The job's ``ok`` record if it needs no run: with ``resume``, any ``ok`` record (the sweeper
    launched the job because it had none, so another sweep wrote it since); without, only one that
    another process wrote during this sweep (newer than ``sweep.json``, both stamped by the same
    file system clock). Else None."""
    path = folder / RECORD_NAME
    if not resume and sweep_file is None:
        return None
    try:
        if not resume and path.stat().st_mtime_ns < sweep_file.stat().st_mtime_ns:  # type: ignore[union-attr]
            return None
        rec = read_record(path)
    except (OSError, ValueError):
        return None
    return rec if rec.get("meta", {}).get("status") == "ok" else None


@dataclass(frozen=True)
class SweepJob:
    """What one sweep job runs, written once: ``execute(cfg, out_dir, choices, overrides,
    job_num, attempt=n)`` (:func:`nirspi_pipe.execute.execute_job`'s parameters)."""

    cfg: Any
    out_dir: Path
    choices: dict[str, str]
    overrides: list[str]
    job_num: int | None = None

    def run(self, execute: Callable[..., dict[str, Any]], attempt: int) -> dict[str, Any]:
        """``execute`` of this job, attempt ``attempt``: the record it wrote."""
        return execute(self.cfg, self.out_dir, self.choices, self.overrides, self.job_num, attempt=attempt)


def run_sweep_job(
    execute: Callable[..., dict[str, Any]],
    cfg: Any,
    out_dir: Path,
    choices: dict[str, str],
    overrides: list[str],
    job_num: int | None = None,
    sweep_file: Path | None = None,
    resume: bool = False,
) -> dict[str, Any]:
    """Run ``execute(cfg, out_dir, choices, overrides, job_num, attempt=n)`` (which writes the
    job's record) as described in the module docstring. Never raises for a failing or crashing
    job; returns the record written (or, when even that could not be written, the one meant)."""
    try:
        job = ClaimedJob.claim(SweepJob(cfg, out_dir, choices, overrides, job_num), sweep_file, resume, wait=True)
    except OutputError as exc:  # disk full, a folder that is a link: this job fails, the others go on
        return unwritten_failure(out_dir, overrides, job_num, exc)
    assert job is not None  # wait=True always takes the lock
    if job.done is not None:
        return job.finish(None)
    if not hasattr(os, "fork"):  # pragma: no cover - Windows: no isolation
        try:
            job.done = job.job.run(execute, job.attempt)
        except BaseException:
            job.lock.release()
            raise
        return job.finish(None)
    pid = job.fork(execute)
    while True:
        try:
            _, status = os.waitpid(pid, 0)
            break
        except InterruptedError:  # pragma: no cover - retried by Python since 3.5
            continue
    return job.finish(status)


#: Wait status of a child whose job runner itself raised (exit code :data:`_CHILD_FAILED`).
CHILD_FAILED_STATUS = _CHILD_FAILED << 8
#: Wait status of a child that could not write its record (exit code :data:`_OUTPUT_FAILED`).
OUTPUT_FAILED_STATUS = _OUTPUT_FAILED << 8


def execute_attempt(execute: Callable[..., dict[str, Any]], job: SweepJob, attempt: int) -> int:
    """Run attempt ``attempt`` of a claimed job in this process (a forked child, or a runner of
    the ``nirspi`` launcher); the wait status a child doing it would give: 0, or
    :data:`CHILD_FAILED_STATUS` when ``execute`` raised (traceback on stderr), or
    :data:`OUTPUT_FAILED_STATUS` when it could not write the record (one line, no traceback)."""
    try:
        job.run(execute, attempt)
    except OutputError as exc:  # disk full, unwritable folder: one line naming the file
        print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
        return OUTPUT_FAILED_STATUS
    except Exception:  # noqa: BLE001 - reported as the crash of this job; a runner goes on
        traceback.print_exc()
        return CHILD_FAILED_STATUS
    return 0


class ClaimedJob:
    """One sweep job between its claim (lock taken, attempt counted) and its end (:meth:`finish`
    with the wait status of the process that ran it: the record, a crash record when that
    process wrote none for this attempt, the lock released).

    :func:`run_sweep_job` runs it in a forked child (:meth:`fork`) and waits; the ``nirspi``
    launcher (:mod:`nirspi_pipe.app.launcher`) hands claimed jobs to runner processes and finishes
    each with 0 when its runner reports it done, or with the runner's wait status when the
    runner died running it."""

    def __init__(self, lock: JobLock, job: SweepJob) -> None:
        self.lock, self.job, self.out_dir = lock, job, job.out_dir
        self.attempt = 0
        self.done: dict[str, Any] | None = None

    @classmethod
    def claim(
        cls, job: SweepJob, sweep_file: Path | None = None, resume: bool = False, wait: bool = True
    ) -> ClaimedJob | None:
        """Take the job folder's lock, then either find the job done (``done``: its ``ok``
        record; nothing to run) or count this attempt (``attempt``). With ``wait=False`` returns
        None, without side effects, when another process holds the lock."""
        out_dir = Path(job.out_dir)
        lock = JobLock(out_dir)
        if not lock.acquire(wait=False):
            if not wait:
                return None
            print(f"nirspi-run: job {out_dir.name} is running in another process; waiting for it", flush=True)
            lock.acquire()
        claimed = cls(lock, replace(job, out_dir=out_dir))
        try:
            claimed.done = _done_ok(out_dir, sweep_file, resume)
            if claimed.done is None:
                claimed.attempt = _bump_attempts(out_dir)
                provenance()  # computed once per process (cached), inherited by every forked child
        except BaseException:
            lock.release()
            raise
        return claimed

    def run_here(self, execute: Callable[..., dict[str, Any]]) -> int:
        """Run the job in this process: :func:`execute_attempt` of its job."""
        return execute_attempt(execute, self.job, self.attempt)

    def fork(self, execute: Callable[..., dict[str, Any]]) -> int:
        """Run the job in a forked child; its pid (wait for it, then :meth:`finish`)."""
        sys.stdout.flush()
        sys.stderr.flush()
        try:
            pid = os.fork()
        except BaseException:
            self.lock.release()
            raise
        if pid == 0:  # pragma: no cover - the child (coverage does not follow forks)
            code = 0
            try:
                status = self.run_here(execute)
                code = 0 if status == 0 else os.WEXITSTATUS(status)
            except BaseException:  # noqa: BLE001 - the child must never return into the worker
                traceback.print_exc()
                code = _CHILD_FAILED
            finally:
                try:
                    sys.stdout.flush()
                    sys.stderr.flush()
                finally:
                    os._exit(code)
        return pid

    def finish(self, status: int | None, deadline_s: float | None = None) -> dict[str, Any]:
        """The job's record once the process that ran it ended it with wait status ``status``
        (None: nothing ran, ``done`` is the record); writes a crash record when that process
        wrote none of this attempt. ``deadline_s``: the process was killed at this deadline
        (:func:`deadline_message`). Releases the lock."""
        try:
            if status is None:
                assert self.done is not None  # nothing ran: claim() found it done
                return self.done
            rec = _own_record(self.out_dir, self.attempt)
            if rec is not None and os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0:
                return rec
            return _record_crash(self.job, status, rec, self.attempt, deadline_s)
        finally:
            self.lock.release()


def _own_record(out_dir: Path, attempt: int) -> dict[str, Any] | None:
    try:
        rec = read_record(out_dir / RECORD_NAME)
    except (OSError, ValueError):
        return None
    return rec if rec.get("meta", {}).get("attempt") == attempt else None


def _record_crash(
    job: SweepJob, status: int, rec: dict[str, Any] | None, attempt: int, deadline_s: float | None = None
) -> dict[str, Any]:
    message, fields = crash_message(status)
    if rec is not None and rec.get("meta", {}).get("status") == "failed":
        return rec  # the child recorded its own failure, then exited non-zero: keep its words
    error_type = "JobCrash"
    if deadline_s is not None:
        message, error_type = deadline_message(deadline_s), "JobTimeout"
        fields["timeout_s"] = deadline_s
    config: dict[str, Any]
    try:
        container = plain_config(job.cfg)
        config = container if isinstance(container, dict) else {}
    except Exception:  # noqa: BLE001 - the record must still be written
        config = {}
    record = new_record(
        config, job.choices, job.overrides, job.job_num, attempt, error=message, error_type=error_type, **fields
    )
    try:
        write_record(job.out_dir, record)
    except OutputError as exc:
        if status != OUTPUT_FAILED_STATUS:  # else the job has just said it, in the same words
            print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
    return record
