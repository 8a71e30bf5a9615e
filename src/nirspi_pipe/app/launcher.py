"""The ``nirspi`` launcher (``hydra/launcher=nirspi``, the default): sweep jobs as forked children.

The nirspi sweeper composes every job's config to key its folder (:mod:`nirspi_pipe.app.sweeper`).
This launcher runs exactly those configs: the sweeping process imports the stage modules once,
then forks one child per job, at most ``n_jobs`` at a time (one per core by default), and waits
for whichever ends first. A job therefore costs no second Hydra composition (86-138 ms each on
the shipped grids, idle; ``nirspi-bench compose``), no worker start-up and no
pickling. Each child is the crash-isolated child every launcher uses (:mod:`nirspi_pipe.app.jobs`):
the folder's lock, the attempt count, and a ``failed`` record naming the signal when it
segfaults or is killed; the other jobs go on. A job still running ``timeout_s`` seconds after it
was sent (``hydra.launcher.timeout_s``, 1800 by default) is killed with its runner and becomes a
``failed`` row naming the deadline; a fresh runner takes the next job.

What it leaves out, compared with ``hydra/launcher=joblib``: no per-job ``.hydra/`` folder or
``<job>.log`` (``record.json`` holds the resolved config, the group choices and the overrides),
and Hydra's per-job callbacks (``on_job_start``/``on_job_end``) are not called; the sweep's
``on_multirun_end`` (which collects the results) is. With another sweeper
(``hydra/sweeper=basic``), :meth:`NirspiLauncherBase.launch` composes each job through Hydra's
config loader first, then runs it the same way.

Where ``os.fork`` does not exist (Windows) the jobs run one after another in the sweeping process.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import multiprocessing
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.plugins.launcher import Launcher
from omegaconf import open_dict
from threadpoolctl import threadpool_limits

from nirspi_pipe.app import ctrlc
from nirspi_pipe.app.jobcomposer import ComposedJob, composed_job
from nirspi_pipe.app.launchsettings import DEFAULT_TIMEOUT_S, check_launcher_settings
from nirspi_pipe.app.objective import objective_values
from nirspi_pipe.app.sweepfile import format_progress
from nirspi_pipe.outputfiles import OutputError, refuse_link

__all__ = ["NirspiLauncherBase"]

log = logging.getLogger(__name__)

#: Seconds between two progress lines (the last one is always printed).
PROGRESS_INTERVAL_S = 2.0


def _execute(
    config: dict[str, Any],
    out_dir: Path,
    choices: dict[str, Any],
    overrides: list[str],
    job_num: int | None,
    attempt: int | None = None,
) -> dict[str, Any]:
    """:func:`nirspi_pipe.app.jobs.execute_job` on a composed job's resolved plain config."""
    from nirspi_pipe.app.jobs import execute_job  # start-up: loads hydra, hydra_plugins (62 ms here)

    return execute_job(config, out_dir, choices, overrides, job_num, attempt=attempt)


class NirspiLauncherBase(Launcher):
    """Runs sweep jobs as forked children of the sweeping process (module docstring).

    Args:
        n_jobs: jobs at once; -1 (default) one per core (``os.cpu_count()``).
        timeout_s: deadline of each job in seconds (:data:`DEFAULT_TIMEOUT_S`); None: none.
    """

    def __init__(self, n_jobs: int = -1, timeout_s: float | None = DEFAULT_TIMEOUT_S) -> None:
        check_launcher_settings(n_jobs, timeout_s)
        self.n_jobs = n_jobs
        self.timeout_s = None if timeout_s is None else float(timeout_s)
        self.hydra_context: Any = None
        self.task_function: Any = None
        self.config: Any = None

    def setup(self, *, hydra_context: Any, task_function: Any, config: Any) -> None:
        self.hydra_context, self.task_function, self.config = hydra_context, task_function, config

    @property
    def workers(self) -> int:
        return self.n_jobs if self.n_jobs > 0 else max(1, os.cpu_count() or 1)

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        """Hydra's launcher interface (any sweeper): compose each job with Hydra's config loader,
        then run it as :meth:`run_composed` does, into ``hydra.sweep.dir/hydra.sweep.subdir``."""
        items = []
        for idx, overrides in enumerate(job_overrides):
            cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
            with open_dict(cfg):
                cfg.hydra.job.num = initial_job_idx + idx
                cfg.hydra.job.id = f"{cfg.hydra.job.name}_{initial_job_idx + idx}"
            # hydranode loads app.configs, whose import runs Hydra's plugin scan, which imports
            # hydra_plugins.nirspi_pipe_sweeper and so this module: a circle at module level wherever
            # start-up: hydra_plugins is installed as a package (a non-editable install; tests/test_install_plugins.py)
            from nirspi_pipe.app.hydranode import refuse_job

            refuse_job(cfg)  # the node this job would run with (issue 41), before anything of it runs
            out_dir = Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)
            items.append((out_dir, initial_job_idx + idx, composed_job(cfg)))
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        return self._run(items, sweep_dir, None, False)

    def run_composed(
        self, jobs: Sequence[tuple[str, list[str], ComposedJob]], sweep_dir: Path, sweep_file: Path, resume: bool
    ) -> list[JobReturn]:
        """Run the nirspi sweeper's composed jobs ``(key, overrides, job)`` into ``sweep_dir/key``
        (job numbers in this order), printing progress as they finish."""
        items = [(Path(sweep_dir) / key, num, job) for num, (key, _ov, job) in enumerate(jobs)]
        return self._run(items, Path(sweep_dir), sweep_file, resume)

    def _run(
        self, items: list[tuple[Path, int, ComposedJob]], sweep_dir: Path, sweep_file: Path | None, resume: bool
    ) -> list[JobReturn]:
        refuse_link(sweep_dir, "sweep folder")
        # Ctrl-C is recorded and raised at the schedule's checks and waits, never lost in a fork
        # (the provenance query's, a runner's): nirspi_pipe.app.ctrlc
        with ctrlc.guarded():
            return self._run_guarded(items, sweep_dir, sweep_file, resume)

    def _run_guarded(
        self, items: list[tuple[Path, int, ComposedJob]], sweep_dir: Path, sweep_file: Path | None, resume: bool
    ) -> list[JobReturn]:
        # start-up: loads hydra, hydra_plugins (62 ms here)
        from nirspi_pipe.app.jobs import (
            ClaimedJob,
            SweepJob,
            run_sweep_job,
            unwritten_failure,
        )

        sweep_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        from nirspi_pipe.execute import warm_up  # start-up: loads 15 modules of ours (29 ms here)

        missing = warm_up([job.config for _, _, job in items])  # each stage's own warm_up (stages.WarmsUp)
        if missing:
            log.debug("not importable (their jobs will say so): %s", ", ".join(missing))
        records: list[dict[str, Any] | None] = [None] * len(items)
        progress = _Progress(len(items))
        started = time.time()

        def finished(i: int, rec: dict[str, Any]) -> None:
            records[i] = rec
            status = rec.get("meta", {}).get("status")
            if status != "ok":
                log.error("job %s failed: %s", items[i][0].name, rec.get("meta", {}).get("error"))
            progress.add(status == "ok", time.time() - started)

        def claim(i: int, wait: bool) -> ClaimedJob | None | dict[str, Any]:
            """The claimed job, None (locked elsewhere), or the failed record of a job whose
            folder cannot be written (disk full, a symbolic link): the other jobs go on."""
            out_dir, num, job = items[i]
            try:
                return ClaimedJob.claim(
                    SweepJob(job.config, out_dir, job.choices, job.task_overrides, num), sweep_file, resume, wait=wait
                )
            except OutputError as exc:
                return unwritten_failure(out_dir, job.task_overrides, num, exc)

        if not hasattr(os, "fork"):  # pragma: no cover - Windows: in-process, one at a time
            for i, (out_dir, num, job) in enumerate(items):
                with ctrlc.interruptible():  # the job runs here: Ctrl-C stops it as it always did
                    rec = run_sweep_job(
                        _execute, job.config, out_dir, job.choices, job.task_overrides, num, sweep_file, resume
                    )
                finished(i, rec)
            return _returns(items, records)
        # BLAS/OpenMP threads per job as loky gives its workers (cores // jobs at once): the jobs
        # do not oversubscribe the cores, and their numbers equal hydra/launcher=joblib's bit for bit
        limits = threadpool_limits(limits=max(1, (os.cpu_count() or 1) // self.workers))
        gc.freeze()  # the runners' garbage collector then leaves the parent's objects (and pages) alone
        log.info("prewarmed in %.2f s; %d jobs, %d at a time", time.perf_counter() - t0, len(items), self.workers)
        pool = _RunnerPool(items, min(self.workers, len(items)), self.timeout_s)
        try:
            _schedule(pool, len(items), claim, finished, self.timeout_s)
        except BaseException:
            for _i, claimed, status, _late in pool.kill():
                claimed.finish(status)
            raise
        finally:
            pool.close()
            limits.restore_original_limits()
            gc.unfreeze()
        progress.flush()
        return _returns(items, records)


def _next_job(
    pool: _RunnerPool, pending: deque[int], deferred: list[int], claim: Callable[[int, bool], Any], finished: Callable
) -> None:
    """Claims the next job (a pending one without waiting; else a deferred one, waiting for its
    lock) and dispatches it to an idle runner; a job already done or unwritable is finished here;
    one locked elsewhere is deferred."""
    if pending:
        i = pending.popleft()
        claimed = claim(i, False)
        if claimed is None:
            deferred.append(i)
            return
    else:
        i = deferred.pop(0)
        with ctrlc.interruptible():  # waits for another process's lock
            claimed = claim(i, True)
    assert claimed is not None  # wait=True always claims
    if isinstance(claimed, dict):
        finished(i, claimed)
    elif claimed.done is not None:
        finished(i, claimed.finish(None))
    else:
        pool.dispatch(i, claimed)


def _schedule(
    pool: _RunnerPool, n: int, claim: Callable[[int, bool], Any], finished: Callable, timeout_s: float | None
) -> None:
    """Runs the jobs ``0 .. n-1`` on the pool: idle runners get the pending jobs, then (when no
    runner is busy) those deferred because another process held their folder's lock."""
    pending = deque(range(n))
    deferred: list[int] = []  # another process holds the folder's lock: waited for at the end
    while pending or deferred or pool.busy:
        while pool.has_idle() and (pending or (deferred and not pool.busy)):
            ctrlc.check()  # a Ctrl-C recorded since (in a fork, say): no further job is sent
            _next_job(pool, pending, deferred, claim, finished)
        if pool.busy:
            for i, claimed, status, late in pool.wait():
                finished(i, claimed.finish(status, timeout_s if late else None))


def _returns(items: list[tuple[Path, int, ComposedJob]], records: list[dict[str, Any] | None]) -> list[JobReturn]:
    """Each job's return: the values of the ``objective`` its config names (what an optimising
    sweeper reads: :func:`nirspi_pipe.app.objective.objective_values`, None for a failed job),
    else its record."""
    return [
        JobReturn(
            overrides=list(job.task_overrides),
            working_dir=str(out_dir),
            task_name="nirspi_pipe",
            status=JobStatus.COMPLETED,
            _return_value=_return_value(job, rec),
        )
        for (out_dir, _num, job), rec in zip(items, records, strict=True)
    ]


def _return_value(job: ComposedJob, rec: dict[str, Any] | None) -> Any:
    if job.config.get("objective") is None:
        return rec
    return objective_values({**(rec or {}), "config": job.config})


def _runner_main(conn: Any, items: list[tuple[Path, int, ComposedJob]]) -> None:
    """A runner: run the jobs the launcher sends (``(index, attempt)``), one at a time, and answer
    ``(index, wait status)`` for each; stop at ``None`` or when the launcher is gone."""
    from nirspi_pipe.app.jobs import SweepJob, execute_attempt  # start-up: loads hydra, hydra_plugins (62 ms here)

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        i, attempt = msg
        out_dir, num, job = items[i]
        status = execute_attempt(_execute, SweepJob(job.config, out_dir, job.choices, job.task_overrides, num), attempt)
        sys.stdout.flush()
        sys.stderr.flush()
        conn.send((i, status))


class _Runner:
    def __init__(self, pid: int, conn: Any) -> None:
        self.pid, self.conn = pid, conn


class _RunnerPool:
    """Runner processes forked from the prewarmed sweeping process. Each runs the jobs it is sent
    one after another, in-process, so that what a job builds once per process (the OpenCL
    context, kernels and their warm-up launch: about 0.1 s, 0.8 s with empty kernel caches;
    module caches) is built once per runner rather than once per job. A runner that dies
    (segfault, ``SIGKILL``, out-of-memory) takes only the job it was running: :meth:`wait`
    reports that job with the runner's wait status (a crash record follows) and a fresh runner
    takes its place. A job still running ``timeout_s`` after it was sent is killed with its runner
    (``SIGKILL``) and reported late; a fresh runner takes its place too."""

    def __init__(self, items: list[tuple[Path, int, ComposedJob]], size: int, timeout_s: float | None = None) -> None:
        self.items = items
        self.timeout_s = timeout_s
        self.idle: list[_Runner] = [self._spawn() for _ in range(size)]
        # conn -> (runner, index, claimed job, deadline on time.monotonic())
        self.running: dict[Any, tuple[_Runner, int, Any, float]] = {}

    @property
    def busy(self) -> bool:
        return bool(self.running)

    def has_idle(self) -> bool:
        return bool(self.idle)

    def _spawn(self) -> _Runner:
        parent_end, child_end = multiprocessing.Pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the runner (coverage does not follow forks)
            code = 0
            try:
                ctrlc.in_child()  # SIGINT as before the launcher's guard: KeyboardInterrupt
                parent_end.close()
                _runner_main(child_end, self.items)
            except KeyboardInterrupt:  # Ctrl-C: the job it ran (if any) is one the interrupt stopped
                code = ctrlc.INTERRUPTED_EXIT
            except BaseException:  # noqa: BLE001 - a runner must never return into the launcher
                code = 70
            finally:
                os._exit(code)
        child_end.close()
        return _Runner(pid, parent_end)

    def dispatch(self, i: int, claimed: Any) -> None:
        """Send job ``i`` (claimed: lock taken, attempt counted) to an idle runner."""
        runner = self.idle.pop()
        try:
            runner.conn.send((i, claimed.attempt))
        except OSError:  # the runner died idle: start another and send it there
            runner.conn.close()
            _reap(runner.pid)
            runner = self._spawn()
            runner.conn.send((i, claimed.attempt))
        deadline = time.monotonic() + self.timeout_s if self.timeout_s is not None else float("inf")
        self.running[runner.conn] = (runner, i, claimed, deadline)

    def wait(self) -> list[tuple[int, Any, int, bool]]:
        """Block until at least one runner answers or dies, or a job passes its deadline;
        ``(index, claimed job, wait status, killed at the deadline)`` of each job that ended."""
        ended = []
        first = min(deadline for *_, deadline in self.running.values())
        timeout = None if first == float("inf") else max(0.0, first - time.monotonic())
        with ctrlc.interruptible():  # Ctrl-C: KeyboardInterrupt at once, the runners are killed
            ready_conns = wait(list(self.running), timeout=timeout)
        for ready in ready_conns:
            runner, i, claimed, _deadline = self.running.pop(ready)
            conn = runner.conn
            try:
                _j, status = conn.recv()
                self.idle.append(runner)
            except (EOFError, OSError):  # the runner died running job i
                status = _reap(runner.pid)
                conn.close()
                self.idle.append(self._spawn())
            ended.append((i, claimed, status, False))
        now = time.monotonic()
        for conn, (runner, i, claimed, deadline) in list(self.running.items()):
            if deadline <= now:  # past its deadline: kill the runner, a fresh one takes its place
                del self.running[conn]
                with contextlib.suppress(ProcessLookupError):
                    os.kill(runner.pid, signal.SIGKILL)
                status = _reap(runner.pid)
                conn.close()
                self.idle.append(self._spawn())
                ended.append((i, claimed, status, True))
        return ended

    def kill(self) -> list[tuple[int, Any, int, bool]]:
        """Stop the runners with jobs in flight (an interrupt); those jobs with their wait status."""
        ended = []
        for conn, (runner, i, claimed, _deadline) in list(self.running.items()):
            try:
                os.kill(runner.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            ended.append((i, claimed, _reap(runner.pid), False))
            conn.close()
        self.running.clear()
        return ended

    def close(self) -> None:
        """Tell the idle runners to stop and wait for them."""
        for runner in self.idle:
            try:
                runner.conn.send(None)
            except OSError:
                pass
            runner.conn.close()
            _reap(runner.pid)
        self.idle.clear()


def _reap(pid: int) -> int:
    """Wait for child ``pid``; its wait status (``SIGKILL``'s when it is already gone)."""
    try:
        return os.waitpid(pid, 0)[1]
    except ChildProcessError:
        return int(signal.SIGKILL)


class _Progress:
    """The sweep's progress line from the launcher's own counts, at most every
    :data:`PROGRESS_INTERVAL_S` (and always for the last job)."""

    def __init__(self, total: int) -> None:
        self.total, self.done, self.failed, self.printed = total, 0, 0, 0
        self._last_print = 0.0
        self._elapsed = 0.0

    def add(self, ok: bool, elapsed_s: float) -> None:
        self.done += 1
        self.failed += not ok
        self._elapsed = elapsed_s
        if time.perf_counter() - self._last_print >= PROGRESS_INTERVAL_S or self.done == self.total:
            self.flush()

    def flush(self) -> None:
        """Print the line if a job finished since the last one."""
        if self.done != self.printed:
            self._last_print, self.printed = time.perf_counter(), self.done
            line = format_progress(self.done, self.failed, self.total, 0, 0, self._elapsed)
            print(f"nirspi-run: {line}", flush=True)
