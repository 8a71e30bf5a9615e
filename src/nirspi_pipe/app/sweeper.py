"""The ``nirspi`` sweeper: Hydra's basic grid sweeper made resumable, keyed, crash-proof and observable.

It expands the sweep like Hydra's ``basic`` sweeper (command-line sweeps plus
``hydra.sweeper.params``), using Hydra's public override parser, then for every job:

* composes its config with Hydra's config loader and keys its output folder
  (``hydra.sweep.subdir=<key>``) by :func:`nirspi_pipe.jobkey.job_key_of`: the hash of the
  resolved config, together with the content hash of every input file it names (recordings,
  meshes, images, weights), so the same job always lands in the same folder and a changed file
  reruns it;
* skips the job when that folder already holds a complete record (``status == "ok"``), so
  rerunning a sweep command recomputes only what is missing or failed; a job that has failed
  ``max_attempts`` times with the same code is not relaunched (a deterministic crasher cannot
  block a sweep); a job that does not compose is a failed record naming the bad override;
* writes ``sweep.json`` in the sweep folder (start time, totals, every job's key and
  overrides), from which a watcher thread prints progress and an ETA as records appear, and which
  :func:`nirspi_pipe.app.results.collect` uses to list jobs that never wrote a record.

Each launched job runs through :func:`nirspi_pipe.app.jobs.run_sweep_job` (a lock per job folder, an
attempt counter, and a forked child so that a segfault or a kill is a failed row). Should the
launcher itself fail (a joblib worker killed from outside), the jobs without a record are
launched again, at most ``max_attempts`` rounds (fewer when a round wrote no record: the
launcher could not start). A job folder that is a symbolic link is refused (not launched; a failed
row naming the link), and nothing is written through it.

The pieces live in their own modules: the grid, the composed job and its key in
:mod:`nirspi_pipe.app.jobcomposer`; ``sweep.json`` and the progress line in
:mod:`nirspi_pipe.app.sweepfile`; the ``sacct`` shim for SLURM in :mod:`nirspi_pipe.app.slurmshim`.

After the sweep the results callback (:class:`nirspi_pipe.app.results.CollectResults`) exits non-zero
when any job failed or is missing, naming how many and why (:data:`launcher_failures` holds why the
launcher failed), unless ``hydra.sweeper.allow_failures=true``.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf

from nirspi_pipe.app.flags import Refused
from nirspi_pipe.app.jobcomposer import (
    ComposedJob,
    ComposeFailure,
    JobRefused,
    choices_of,
    composed_job,
    error_line,
    error_type,
    expand_grid,
    resolve_plain,
    set_plain,
    subdir_override,
)
from nirspi_pipe.app.slurmshim import quiet_sacct_without_accounting
from nirspi_pipe.app.sweepfile import SWEEP_FILE, ProgressWatcher, record_status
from nirspi_pipe.jobkey import InputHasher, config_hash, job_key_of
from nirspi_pipe.outputfiles import OutputError, atomic_write, refuse_link
from nirspi_pipe.provenance import provenance
from nirspi_pipe.records import RECORD_NAME, write_record
from nirspi_pipe.strictjson import dumps_strict

__all__ = ["NirspiSweeperBase", "launcher_failures"]

log = logging.getLogger(__name__)

#: Why the launcher failed in the last sweep of this process (one line each, in order); the
#: results callback names them when the sweep exits non-zero.
launcher_failures: list[str] = []


#: The sweeper a keying worker process (forked by ``NirspiSweeperBase._prepare_parallel``) keys for.
_keying_sweeper: Any = None


def _set_keying_sweeper(sweeper: Any) -> None:
    global _keying_sweeper
    _keying_sweeper = sweeper


def _key_chunk(chunk: list[tuple[int, list[str]]]) -> list[tuple[int, Any, ComposedJob | None]]:
    """Key a worker's share of the jobs (its structural override sets, composed once each)."""
    done = _keying_sweeper._prepare_serial([ov for _, ov in chunk], True)  # our own class
    return [
        (i, key if isinstance(key, str) else ComposeFailure(type(key).__name__, str(key)), job)
        for (i, _), (key, job) in zip(chunk, done, strict=True)
    ]


class NirspiSweeperBase(Sweeper):
    """Grid sweeper with keyed job folders, resume, crash isolation and progress (see the module
    docstring). It uses Hydra's public API only: the sweeper plugin interface, the override parser
    and the config loader handed over in ``hydra_context``."""

    def __init__(
        self,
        max_batch_size: int | None = None,
        params: dict[str, str] | None = None,
        resume: bool = True,
        experiments: list[str] | None = None,
        max_attempts: int = 3,
        allow_failures: bool = False,
        direction: Any = None,
    ) -> None:
        self.max_batch_size = max_batch_size
        self.direction = direction  # objective's directions: read by the results callback (pareto column)
        self.params = dict(params or {})
        self.resume = resume
        self.experiments = list(experiments or [])
        if not isinstance(max_attempts, int) or max_attempts < 1:
            raise ValueError(f"hydra.sweeper.max_attempts={max_attempts!r} is not allowed; allowed: an integer >= 1")
        self.max_attempts = max_attempts
        if not isinstance(allow_failures, bool):
            raise ValueError(f"hydra.sweeper.allow_failures={allow_failures!r} is not allowed; allowed: true or false")
        self.allow_failures = allow_failures  # read by the results callback (CollectResults)
        self.hydra_context: Any = None
        self.config: Any = None
        self.launcher: Any = None
        self._groups: dict[str, set[str]] = {}

    def setup(self, *, hydra_context: Any, task_function: Any, config: Any) -> None:
        self.hydra_context = hydra_context
        self.config = config
        if "slurm" in str(config.hydra.launcher.get("_target_", "")).lower():
            quiet_sacct_without_accounting()
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    # -- expansion ------------------------------------------------------------------------------

    def _parser(self) -> OverridesParser:
        return OverridesParser.create(config_loader=self.hydra_context.config_loader)

    def _parse_one(self, text: str) -> Any:
        """One job override, parsed once per sweep: a grid's jobs share their override strings
        (``scan=spiral`` in a quarter of Figure 9's 1280 jobs), and Hydra's parser took ~3 ms per
        job, twice per job (grouping, then composing), serially in the sweeping process."""
        cache: dict[str, Any] = self.__dict__.setdefault("_parsed_overrides", {})
        if text not in cache:
            cache[text] = self._parser().parse_overrides([text])[0]
        return cache[text]

    def _grid(self, params: dict[str, str], arguments: list[str]) -> list[list[str]]:
        params_conf = [f"{k}={v}" for k, v in params.items()]
        params_conf.extend(arguments)
        return expand_grid(self._parser().parse_overrides(params_conf))

    def _expand(self, arguments: list[str]) -> list[list[str]]:
        """Every job's overrides. With ``experiments`` (a meta-experiment such as ``paper``),
        the union of each listed experiment's own grid, each job tagged ``+experiment=<name>``;
        command-line overrides other than the experiment apply to all of them, sweeps included: a
        command-line sweep of a key an experiment also sweeps replaces the experiment's values
        (``+experiment=paper 'seed=range(20,30)'`` runs every table on seeds 20-29)."""
        if not self.experiments:
            return self._grid(self.params, arguments)
        shared = [a for a in arguments if not a.lstrip("+~").startswith("experiment=")]
        # each experiment's own grid is read from its config, composed without the command-line
        # sweeps (Hydra composes one value per key: a list there is "ambiguous"); the sweeps then
        # join the grid below, after the experiment's params, so that they win
        fixed = [a for a in shared if not self._parse_one(a).is_sweep_override()]
        loader = self.hydra_context.config_loader
        jobs: list[list[str]] = []
        for name in self.experiments:
            sub = loader.load_sweep_config(self.config, [f"+experiment={name}", *fixed])
            raw = cast("dict[Any, Any]", OmegaConf.to_container(sub.hydra.sweeper.params or {}, resolve=False))
            params = {str(k): str(v) for k, v in raw.items()}
            jobs.extend([f"+experiment={name}", *job] for job in self._grid(params, shared))
        return jobs

    # -- composition ----------------------------------------------------------------------------

    def _is_group(self, name: str) -> bool:
        """Whether ``name`` (``scene``, ``hydra/launcher``) is a config group (public loader API),
        or one the sweep's config chose an option of: ``experiment`` and ``mechanism`` are groups
        of the search path that ``conf/config.yaml`` adds, which the loader does not list (each of
        scan_order's 480 jobs, ``mechanism=...``, was composed in full: 53 s of keying)."""
        parent, _, leaf = name.rpartition("/")
        if parent not in self._groups:
            groups = set(self.hydra_context.config_loader.list_groups(parent))
            for chosen in self.config.hydra.runtime.choices if self.config is not None else ():
                above, _, group = str(chosen).rpartition("/")
                if above == parent:
                    groups.add(group)
            self._groups[parent] = groups
        return leaf in self._groups[parent]

    def compose(self, overrides: list[str]) -> Any:
        """A job's config exactly as Hydra composes it for the launcher
        (``config_loader.load_sweep_config``), its Hydra node checked as the job's own
        (:func:`nirspi_pipe.app.hydranode.check_job`): :class:`JobRefused` otherwise, which
        :meth:`prepare` turns into one line and exit 2 (the sweep stops before any job runs)."""
        cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
        # hydranode loads app.configs, whose import runs Hydra's plugin scan, which imports
        # hydra_plugins.nirspi_pipe_sweeper and so this module: a circle at module level wherever
        # start-up: hydra_plugins is installed as a package (a non-editable install; tests/test_install_plugins.py)
        from nirspi_pipe.app.hydranode import check_job

        try:
            check_job(cfg.hydra, cfg)
        except Refused as exc:
            raise JobRefused(str(exc)) from None
        return cfg

    def _composed(self, overrides: list[str]) -> ComposedJob:
        """:meth:`compose`, as a :class:`ComposedJob`."""
        return composed_job(self.compose(overrides))

    def _compose(self, overrides: list[str], bases: dict[tuple[str, ...], Any]) -> ComposedJob:
        """:meth:`compose`, fast for grids.

        Hydra composes the defaults list (group choices, ``+``/``~`` overrides) and then applies
        plain ``key=value`` overrides with ``OmegaConf.update(merge=True)``. A full composition
        costs about 0.1 s a job (86-138 ms on the shipped grids, idle; ``nirspi-bench compose``), so for a grid of N jobs we compose
        once per distinct set of structural overrides (cached in ``bases``, as a plain dict with
        interpolations unresolved) and set the plain values on a copy before resolving, as Hydra
        does. Anything unusual (a value that is a mapping, a key the config does not have, a
        mapping replaced by a value) falls back to :meth:`compose`, which reports errors as
        Hydra does. ``tests/test_sweeper_equivalence.py`` holds that the configs agree with
        Hydra's ``compose`` on jobs drawn from every shipped experiment's grid (``nirspi-bench
        compose --check-all``: on every job).
        """
        split = self._split(overrides)
        if split is None:
            return self._composed(overrides)
        base_key, updates, task = split
        if base_key not in bases:
            cfg = self.compose(list(base_key))
            raw = cast("dict[str, Any]", OmegaConf.to_container(cfg, resolve=False))
            raw.pop("hydra", None)
            bases[base_key] = (raw, choices_of(cfg))
        raw, choices = bases[base_key]
        plain_cfg = dict(raw)  # set_plain copies what it changes below the top (copy on write)
        for ov in updates:
            if not set_plain(plain_cfg, str(ov.key_or_group), ov.value()):
                return self._composed(overrides)
        try:
            resolved = resolve_plain(plain_cfg)
        except Exception:  # noqa: BLE001 - let Hydra's composition say what is wrong
            return self._composed(overrides)
        return ComposedJob(resolved, dict(choices), task)

    def _split(self, overrides: list[str]) -> tuple[tuple[str, ...], list[Any], list[str]] | None:
        """``(structural overrides, parsed plain value overrides, task overrides)`` of a job, from
        one parse (None: unparsable). The task overrides are all but ``hydra.*``, as Hydra hands
        them to the task (``hydra.overrides.task``)."""
        try:
            parsed = [self._parse_one(text) for text in overrides]
        except Exception:  # noqa: BLE001 - Hydra reports it properly when it composes
            return None
        structural: list[str] = []
        updates: list[Any] = []
        plain_texts: list[str] = []
        task: list[str] = []
        for ov, text in zip(parsed, overrides, strict=True):
            if not ov.is_hydra_override():
                task.append(text)
            plain = (
                not (ov.is_add() or ov.is_delete() or ov.is_force_add())
                and ov.package is None
                and not ov.key_or_group.startswith("hydra")
                and not self._is_group(ov.key_or_group)
            )
            if plain:
                updates.append(ov)
                plain_texts.append(text)
            else:
                if plain_texts and not ov.is_hydra_override() and not self._is_group(ov.key_or_group):
                    # Hydra applies ``key=value``, ``+key``, ``++key`` and ``~key`` in their order
                    # (``seed=3 ++seed=5`` is 5): the plain ones before this one are composed with it
                    structural.extend(plain_texts)
                    updates.clear()
                    plain_texts.clear()
                structural.append(text)
        return tuple(structural), updates, task

    def _compose_failure(self, overrides: list[str], exc: Exception) -> str:
        """One line naming the first override with which the job stops composing."""
        bad = None
        for i in range(len(overrides)):
            try:
                self.compose(overrides[: i + 1])
            except Exception:  # noqa: BLE001 - found it
                bad = overrides[i]
                break
        where = f"override {bad!r}" if bad else f"overrides {' '.join(overrides)!r}"
        return f"job does not compose: {where}: {error_line(str(exc))}"

    def job_keys(self, jobs: list[list[str]], fast: bool = True) -> list[str | Exception]:
        """The folder key of each job (or the exception that stopped it composing)."""
        return [key for key, _ in self.prepare(jobs, fast)]

    def prepare(
        self, jobs: list[list[str]], fast: bool = True, workers: int | None = None
    ) -> list[tuple[str | Exception, ComposedJob | None]]:
        """Each job's folder key and composed config (or the exception that stopped it composing).

        With ``fast`` and more than one distinct set of structural overrides, the sets are
        composed in ``workers`` forked processes (default: one per core), each keying the jobs of
        its sets: composition is pure Python and the sets are independent (the paper sweep's
        keying went from 18 s to 12 s on 2 cores, ``nirspi-bench paper --experiment paper``)."""
        workers = workers or os.cpu_count() or 1
        try:
            if fast and workers > 1 and len(jobs) > 1 and hasattr(os, "fork"):
                groups: dict[tuple[str, ...], list[int]] = {}
                for i, overrides in enumerate(jobs):
                    split = self._split(overrides)
                    groups.setdefault(split[0] if split is not None else ("#unparsable", str(i)), []).append(i)
                if len(groups) > 1:
                    return self._prepare_parallel(jobs, list(groups.values()), workers)
            return self._prepare_serial(jobs, fast)
        except JobRefused as exc:  # raised in a keying worker too (pickled back by the pool): one line
            print(f"nirspi-run: error: job refused: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None

    def _prepare_serial(self, jobs: list[list[str]], fast: bool) -> list[tuple[str | Exception, ComposedJob | None]]:
        bases: dict[tuple[str, ...], Any] = {}
        hasher = InputHasher()
        out: list[tuple[str | Exception, ComposedJob | None]] = []
        for overrides in jobs:
            try:
                job = self._compose(overrides, bases) if fast else self._composed(overrides)
                out.append((job_key_of(job.config, hasher.hashes(job.config)), job))
            except JobRefused:  # not a failed row: the sweep stops (prepare)
                raise
            except Exception as exc:  # noqa: BLE001 - a failed row, the sweep goes on
                out.append((exc, None))
        return out

    def _prepare_parallel(
        self, jobs: list[list[str]], groups: list[list[int]], workers: int
    ) -> list[tuple[str | Exception, ComposedJob | None]]:

        # largest groups first, each to the least loaded worker
        chunks: list[list[int]] = [[] for _ in range(min(workers, len(groups)))]
        for group in sorted(groups, key=len, reverse=True):
            min(chunks, key=len).extend(group)
        ctx = multiprocessing.get_context("fork")
        with ctx.Pool(len(chunks), initializer=_set_keying_sweeper, initargs=(self,)) as pool:
            parts = pool.map(_key_chunk, [[(i, jobs[i]) for i in chunk] for chunk in chunks])
        out: list[tuple[str | Exception, ComposedJob | None]] = [(RuntimeError("not keyed"), None)] * len(jobs)
        for part in parts:
            for i, key, job in part:
                out[i] = (key, job)
        return out

    # -- the sweep ------------------------------------------------------------------------------

    def sweep(self, arguments: list[str]) -> Any:
        assert self.config is not None and self.launcher is not None
        assert self.hydra_context is not None
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        launcher_failures.clear()
        try:
            return self._sweep(sweep_dir, arguments)
        except OutputError as exc:  # unwritable sweep folder, disk full: one line, no traceback
            print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(1) from None

    def _sweep(self, sweep_dir: Path, arguments: list[str]) -> Any:
        """Expand the grid, key every job by its composed config, write ``sweep.json`` with each
        job's fate (run, skipped, duplicate, uncomposable, refused, given up), say it in one line,
        and launch what is to run."""
        atomic_write(sweep_dir / "multirun.yaml", OmegaConf.to_yaml(self.config))
        try:
            grid = self._expand(arguments)
        except Exception as exc:  # noqa: BLE001 - a grid that cannot be expanded: nothing to run
            print(f"nirspi-run: error: the sweep cannot be expanded: {error_line(str(exc))}", file=sys.stderr)
            raise SystemExit(2) from None
        t0 = time.perf_counter()
        # a launcher that can run composed jobs (the nirspi launcher, nirspi_pipe.app.launcher) gets them
        run_composed = getattr(self.launcher, "run_composed", None)
        prepared = self.prepare(grid, workers=getattr(self.launcher, "workers", None) if run_composed else None)
        composed: dict[str, ComposedJob] = {}  # the first job of each key runs (as it is launched below)
        for key, prepared_job in prepared:
            if isinstance(key, str) and prepared_job is not None:
                composed.setdefault(key, prepared_job)
        keying_s = time.perf_counter() - t0
        log.info("keyed %d jobs in %.1f s", len(grid), keying_s)

        started = time.time()
        jobs, to_launch, n_bad, n_links = self._plan(sweep_dir, grid, [key for key, _ in prepared])
        info = {
            "started": started,
            "experiments": self.experiments,
            "total": len(jobs),
            "to_run": len(to_launch),
            "keying_s": round(keying_s, 3),
            "max_attempts": self.max_attempts,
            "jobs": jobs,
        }
        sweep_file = sweep_dir / SWEEP_FILE
        atomic_write(sweep_file, dumps_strict(info, indent=1))
        self._announce(sweep_dir, jobs, len(to_launch), n_bad, n_links, keying_s)
        returns: list[Sequence[Any]] = []
        if not to_launch:
            return returns
        if run_composed is not None:  # it runs the composed jobs and reports progress itself
            returns.append(
                run_composed([(key, ov, composed[key]) for key, ov in to_launch], sweep_dir, sweep_file, self.resume)
            )
            return returns
        watcher = ProgressWatcher(sweep_dir)
        watcher.start()
        try:
            self._launch_with_retries(sweep_dir, sweep_file, to_launch, returns)
        finally:
            watcher.stop()
        return returns

    def _plan(
        self, sweep_dir: Path, grid: list[list[str]], keys: list[str | Exception]
    ) -> tuple[list[dict[str, Any]], list[tuple[str, list[str]]], int, int]:
        """Each job's entry in ``sweep.json``, the ``(key, overrides)`` to launch, and the numbers of
        distinct jobs that do not compose and of job folders refused. A job that does not compose
        gets a failed record; a job folder that is a link is refused; a job whose ``ok`` record
        exists is skipped with ``resume``; a repeated config runs once; a job that used up
        ``max_attempts`` is not retried."""
        from nirspi_pipe.app.jobs import attempts_with_this_code  # start-up: loads hydra, hydra_plugins (58 ms here)

        jobs: list[dict[str, Any]] = []
        to_launch: list[tuple[str, list[str]]] = []
        seen: set[str] = set()
        n_bad = n_links = 0
        for overrides, key in zip(grid, keys, strict=True):
            job: dict[str, Any] = {"overrides": overrides}
            if isinstance(key, Exception):
                failure, key = key, config_hash({"uncomposable": overrides})
                job.update(key=key, skipped=False, launched=False, uncomposable=True)
                if key not in seen:
                    n_bad += 1
                    message = self._compose_failure(overrides, failure)
                    log.error("%s", message)
                    _record_uncomposable(sweep_dir / key, overrides, message, error_type(failure))
            elif (sweep_dir / key).is_symlink():  # never written through, never read through
                job.update(key=key, skipped=False, launched=False, refused=True)
                if key not in seen:
                    n_links += 1
                    try:
                        refuse_link(sweep_dir / key, "job folder")
                    except OutputError as exc:
                        print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
            else:
                status = record_status(sweep_dir / key)
                skipped = self.resume and status == "ok"
                job.update(key=key, skipped=skipped)
                if key in seen:
                    job["duplicate"] = True  # identical config (e.g. two experiments share a grid): run once
                elif not skipped and attempts_with_this_code(sweep_dir / key) >= self.max_attempts:
                    job.update(launched=False, gave_up=True)  # its failed record stays
                    if status is None:  # killed each time before it could write one
                        _record_uncomposable(
                            sweep_dir / key,
                            overrides,
                            f"gave up after {self.max_attempts} attempts that wrote no record (killed each time?)",
                            "JobCrash",
                        )
                elif not skipped:
                    to_launch.append((key, overrides))
            seen.add(job["key"])
            jobs.append(job)
        return jobs, to_launch, n_bad, n_links

    def _announce(
        self, sweep_dir: Path, jobs: list[dict[str, Any]], n_run: int, n_bad: int, n_links: int, keying_s: float
    ) -> None:
        """The sweep's one line: how many jobs run, are skipped, repeat, fail to compose, are
        refused or given up."""
        n_dup = sum(bool(j.get("duplicate")) for j in jobs)
        if n_dup:
            log.warning("%d jobs of this sweep repeat another job's config; each config runs once", n_dup)
        n_gave_up = sum(bool(j.get("gave_up")) for j in jobs)
        n_skip = sum(bool(j["skipped"]) and not j.get("duplicate") for j in jobs)
        print(
            f"nirspi-run: sweep of {len(jobs)} jobs in {sweep_dir}: {n_run} to run"
            + (f", {n_skip} skipped (already complete)" if n_skip else "")
            + (f", {n_dup} identical to another job (run once)" if n_dup else "")
            + (f", {n_bad} do not compose (failed)" if n_bad else "")
            + (f", {n_links} refused (job folder is a symbolic link)" if n_links else "")
            + (
                f", {n_gave_up} failed {self.max_attempts} times and are not retried (hydra.sweeper.max_attempts)"
                if n_gave_up
                else ""
            )
            + f" [keyed in {keying_s:.1f} s]",
            flush=True,
        )

    def _launch_with_retries(
        self, sweep_dir: Path, sweep_file: Path, to_launch: list[tuple[str, list[str]]], returns: list[Sequence[Any]]
    ) -> None:
        """Launch the jobs; when the launcher fails (e.g. a joblib worker killed from outside),
        launch again the jobs that wrote no record in this sweep and may still be attempted,
        unless that round wrote no record at all (the launcher could not start: it would fail
        again), at most ``max_attempts`` rounds."""
        from nirspi_pipe.app.jobs import attempts_with_this_code  # start-up: loads hydra, hydra_plugins (58 ms here)

        pending = to_launch
        for round_ in range(self.max_attempts):
            if not self._launch(pending, returns):
                break
            left = [(key, ov) for key, ov in pending if not _written_since(sweep_dir / key / RECORD_NAME, sweep_file)]
            if len(left) == len(pending):
                break
            pending = [(key, ov) for key, ov in left if attempts_with_this_code(sweep_dir / key) < self.max_attempts]
            if not pending or round_ + 1 == self.max_attempts:
                break
            print(f"nirspi-run: launching the {len(pending)} jobs without a record again", flush=True)

    def _launch(self, jobs: list[tuple[str, list[str]]], returns: list[Sequence[Any]]) -> bool:
        """Launch ``jobs`` in batches; True when the launcher raised (reported in one line)."""
        batch_size = self.max_batch_size or len(jobs)
        for start in range(0, len(jobs), batch_size):
            batch = [[*ov, subdir_override(key)] for key, ov in jobs[start : start + batch_size]]
            try:
                returns.append(self.launcher.launch(batch, initial_job_idx=start))
            except Exception as exc:  # noqa: BLE001 - the records say which jobs finished
                first = str(exc).strip().splitlines()
                why = f"{type(exc).__name__}: {first[0] if first else ''}"
                launcher_failures.append(why)
                print(f"nirspi-run: warning: the launcher failed: {why}", file=sys.stderr, flush=True)
                return True
        return False


def _written_since(path: Path, reference: Path) -> bool:
    try:
        return path.stat().st_mtime_ns >= reference.stat().st_mtime_ns
    except OSError:
        return False


def _record_uncomposable(folder: Path, overrides: list[str], message: str, error_type: str) -> None:
    """A failed record for a job whose config does not compose (no config, the error)."""
    record = {
        "config": {},
        "choices": {},
        "metrics": {},
        "timings_ms": {},
        "derived": {},
        "info": {},
        "meta": {
            "config_hash": None,
            "job_key": folder.name,
            **provenance(),
            "status": "failed",
            "error": message,
            "error_type": error_type,
            "warnings": [],
            "overrides": overrides,
        },
    }
    write_record(folder, record)
