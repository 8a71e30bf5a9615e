"""Optuna studies that last: ``hydra/sweeper=optuna`` driven through Optuna's public API.

The sweeper (:class:`StudySweeperBase`, ``conf/hydra/sweeper/optuna.yaml``) is the ``nirspi``
grid sweeper's machinery (job folders keyed by config hash, a record per job, crash isolation,
``sweep.json``, the results callback) with Optuna choosing the jobs:

* **A study in a database.** ``hydra.sweeper.storage: null`` (the default) keeps the study in
  SQLite inside the sweep folder, ``<sweep>/<study_name>.db``; ``study_name: null`` names it after
  the sweep folder. ``create_study(load_if_exists=True)`` continues it: rerunning the same command
  (the same ``hydra.sweep.dir``) runs only the trials that ``n_trials`` (the study's total) still
  asks for, so a finished study runs none and a larger ``n_trials`` adds the difference. A trial's
  job lands in its keyed folder, so a configuration Optuna asks for again reuses its record
  instead of being timed again. A database URL may be named for a study shared between machines
  (:func:`~nirspi_pipe.app.storage.check_storage`: ``postgresql``/``mysql`` schemes, or ``sqlite``
  on a file inside the sweep folder; anything else is refused in one line).
* **Objectives checked before the first trial.** Before the study asks for a trial, one job (the
  search space's first configuration, in its keyed folder, so its record is reused when a trial
  asks for it) shows which record keys this experiment writes; an ``objective`` naming a key that
  record lacks is refused in one line (exit 2) naming the nearest keys, and no trial is run.
* **Failed trials.** A job that failed, or whose record lacks a value of the objective, is a
  ``FAIL`` trial; the results callback exits 1 when more than ``max_failure_rate`` of the trials
  did not finish ok.
* **Repeats.** ``repeats: k`` runs each trial's configuration ``k`` times (folders keyed by the
  config hash and the repeat) and tells Optuna the median of each objective over the repeats
  (:func:`~nirspi_pipe.app.searchspace.median_values`); the results' ``pareto`` column marks
  configurations on the front of those medians (:func:`nirspi_pipe.app.results.mark_pareto`).
* **Ctrl-C** ends the sweep with one line: how many trials finished, where the study is, and the
  command that resumes it; the results table is written for what finished.
* **Several workers** (e.g. SLURM jobs each running the same command on one database) share one
  study: each asks for trials until the study holds ``n_trials`` (finished or running).

The search space and the objectives' checks are pure functions in
:mod:`nirspi_pipe.app.searchspace`; the storage rule is :mod:`nirspi_pipe.app.storage`.

Only Optuna's public API is used (``create_study``, ``ask``, ``tell``, ``get_trials``,
``Trial.suggest_*``), which Optuna 2.10 and later versions share.
"""

from __future__ import annotations

import logging
import os
import shlex
import signal
import socket
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf

from nirspi_pipe.app import ctrlc
from nirspi_pipe.app.objective import directions_of, objective_names
from nirspi_pipe.app.searchspace import (
    Dimension,
    as_override_value,
    check_objective_keys,
    dimension_of,
    median_values,
    repeat_key,
)
from nirspi_pipe.app.storage import StorageError, shown_url, storage_url
from nirspi_pipe.app.sweeper import NirspiSweeperBase
from nirspi_pipe.jobkey import InputHasher, job_key_of
from nirspi_pipe.outputfiles import OutputError, atomic_write
from nirspi_pipe.records import RECORD_NAME, read_record
from nirspi_pipe.strictjson import dumps_strict

__all__ = ["SWEEPER_CONFIG", "StudySweeperBase", "register_config"]


#: ``hydra/sweeper=optuna``: this sweeper's config, registered over hydra-optuna-sweeper's node of
#: that name (:func:`register_config`); the samplers are the plugin's ``hydra/sweeper/sampler`` options.
SWEEPER_CONFIG: dict[str, Any] = {
    "defaults": [{"sampler": "tpe"}],  # hydra/sweeper/sampler=tpe|random|cmaes|nsgaii|motpe
    "_target_": "hydra_plugins.nirspi_pipe_sweeper.NirspiOptunaSweeper",
    "direction": "minimize",  # one per objective key: minimize or maximize
    "n_trials": 20,  # trials the study holds in all: a rerun runs only the ones still missing
    "n_jobs": 2,  # trials asked of Optuna at once (the launcher runs their jobs together)
    "storage": None,  # null: SQLite <sweep folder>/<study_name>.db; postgresql://... or mysql://...
    "study_name": None,  # null: the sweep folder's name
    "max_failure_rate": 0.0,  # share of failed trials that still exits 0
    "repeats": 1,  # jobs per trial (same config, own folders); Optuna is told each objective's median
    "max_attempts": 3,  # a job that failed this many times with the same code is not relaunched
    "params": None,  # experiment files put their search space here: {key: "interval(0,1)"}
}


def register_config() -> None:
    """Store :data:`SWEEPER_CONFIG` as ``hydra/sweeper=optuna`` in Hydra's ConfigStore, after the
    Hydra plugin's own node of that name (imported first, so that ours is the one kept whichever
    order Hydra's plugin scan imports the two packages in)."""
    # start-up: Hydra's ConfigStore, at the plugin scan
    from hydra.core.config_store import ConfigStore

    try:
        # start-up: hydra-optuna-sweeper's sampler configs (hydra/sweeper/sampler), when it is installed
        import hydra_plugins.hydra_optuna_sweeper.config  # noqa: F401
    except ImportError:
        pass
    ConfigStore.instance().store(group="hydra/sweeper", name="optuna", node=SWEEPER_CONFIG, provider="nirspi-pipe")
    # Hydra instantiates the sampler before the sweep: Optuna's "``multivariate`` option is an
    # experimental feature" (pareto_search sets it) would be the sweep's first line
    warnings.filterwarnings("ignore", message=r".*is an experimental feature", module=r"optuna\.")


log = logging.getLogger(__name__)


def _read(folder: Path) -> dict[str, Any] | None:
    try:
        return read_record(folder / RECORD_NAME)
    except (OSError, ValueError):
        return None


def _stopped(record: dict[str, Any] | None) -> bool:
    """Whether ``record`` is the launcher's crash record of a job that Ctrl-C stopped: its runner
    ended with :data:`~nirspi_pipe.app.ctrlc.INTERRUPTED_EXIT` (``KeyboardInterrupt``), or by
    ``SIGINT``, or by the ``SIGTERM`` the launcher sends its runners on an interrupt. Such a job
    did not fail: its trial is interrupted, and a resumed study asks for a trial in its place."""
    meta = (record or {}).get("meta") or {}
    return meta.get("error_type") == "JobCrash" and (
        meta.get("exit_code") == ctrlc.INTERRUPTED_EXIT
        or meta.get("signal") in (int(signal.SIGINT), int(signal.SIGTERM))
    )


# -- the sweeper --------------------------------------------------------------------------------

#: Trial states that count toward ``n_trials`` (finished, or running in a live worker).
_HOST = socket.gethostname()


def _alive(host: Any, pid: Any) -> bool:
    """Whether the worker that owns a running trial may still be running: another host's, or a
    live process of this host."""
    if host != _HOST or not isinstance(pid, int):
        return host != _HOST
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _import_optuna() -> Any:
    """The optuna module; without it, one line naming the extra to install and exit (2)."""
    try:
        # optional dependency: pip install '.[optuna]'
        import optuna
    except ImportError as exc:
        print(
            f"nirspi-run: error: hydra/sweeper=optuna needs Optuna ({exc}); pip install '.[optuna]'",
            file=sys.stderr,
        )
        raise SystemExit(2) from None
    return optuna


@dataclass(frozen=True)
class _Batch:
    """What every batch of one study's trials shares: its folder, start, storage and space."""

    sweep_dir: Path
    started: float
    url: str
    dims: list[Dimension]
    fixed: list[str]
    names: list[str]


class StudySweeperBase(NirspiSweeperBase):
    """``hydra/sweeper=optuna``: an Optuna study over keyed job folders (module docstring)."""

    def __init__(
        self,
        sampler: Any = None,
        direction: Any = "minimize",
        storage: Any = None,
        study_name: str | None = None,
        n_trials: int = 20,
        n_jobs: int = 2,
        max_failure_rate: float = 0.0,
        params: dict[str, str] | None = None,
        repeats: int = 1,
        max_attempts: int = 3,
        pruner: Any = None,
    ) -> None:
        super().__init__(params=params, resume=True, max_attempts=max_attempts, direction=direction)
        self.sampler = sampler
        self.pruner = pruner
        self.storage = storage
        self.study_name = study_name
        for key, value in (("n_trials", n_trials), ("n_jobs", n_jobs), ("repeats", repeats)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"hydra.sweeper.{key}={value!r} is not allowed; allowed: an integer >= 1")
        self.n_trials, self.n_jobs, self.repeats = n_trials, n_jobs, repeats
        self.max_failure_rate = max_failure_rate

    # -- helpers --------------------------------------------------------------------------------

    def _resume_command(self, sweep_dir: Path) -> str:
        args = [a for a in sys.argv[1:]]
        if not any(a.startswith("hydra.sweep.dir=") for a in args):
            args.append(f"hydra.sweep.dir={sweep_dir}")
        return shlex.join(["nirspi-run", *args])

    def _run_jobs(
        self, sweep_dir: Path, sweep_file: Path, jobs: list[tuple[str, list[str]]], composed: dict[str, Any]
    ) -> None:
        """Run ``(key, overrides)`` jobs into their keyed folders (an ``ok`` record is reused)."""
        if not jobs:
            return
        run_composed = getattr(self.launcher, "run_composed", None)
        if run_composed is not None and all(key in composed for key, _ in jobs):
            run_composed([(key, ov, composed[key]) for key, ov in jobs], sweep_dir, sweep_file, True)
            return  # the nirspi launcher checks for Ctrl-C itself, and waits for its runners interruptibly
        with ctrlc.interruptible():  # another launcher (joblib, SLURM) waits: Ctrl-C stops it at once, as before
            self._launch_with_retries(sweep_dir, sweep_file, jobs, [])

    def _prepare_trials(
        self, sweep_dir: Path, overrides: list[list[str]]
    ) -> tuple[list[list[tuple[str, list[str]]]], dict[str, Any], list[str | None]]:
        """Each trial's jobs ``(folder key, overrides)`` (``repeats`` of them), the composed
        configs by key, and why a trial does not compose (None when it does)."""
        # serially: a batch is a few trials, and forking a keying pool after the database is open
        # hung (a lock held in the parent at fork). The composed bases (one full Hydra composition
        # per set of group choices, ~2 s each at load 7) are kept across batches: 31 of a 24-trial
        # study's 52 s went to composing them again for every batch
        bases: dict[tuple[str, ...], Any] = self.__dict__.setdefault("_bases", {})
        hasher = self.__dict__.setdefault("_hasher", InputHasher())
        prepared: list[tuple[str | Exception, Any]] = []
        for ov in overrides:
            ctrlc.check()  # a composition takes a second or two: a Ctrl-C ends the study before the next
            try:
                job = self._compose(ov, bases)
                prepared.append((job_key_of(job.config, hasher.hashes(job.config)), job))
            except Exception as exc:  # noqa: BLE001 - a failed trial, the study goes on
                prepared.append((exc, None))
        jobs: list[list[tuple[str, list[str]]]] = []
        composed: dict[str, Any] = {}
        errors: list[str | None] = []
        for ov, (key, job) in zip(overrides, prepared, strict=True):
            if not isinstance(key, str) or job is None:
                jobs.append([])
                errors.append(self._compose_failure(ov, key if isinstance(key, Exception) else ValueError(str(key))))
                continue
            keys = [repeat_key(key, r) for r in range(self.repeats)]
            for k in keys:
                composed[k] = job
            jobs.append([(k, ov) for k in keys])
            errors.append(None)
        return jobs, composed, errors

    def _write_sweep_file(self, sweep_dir: Path, study: Any, started: float, url: str) -> None:
        """List the jobs of the study's trials in ``sweep.json``: the ones collected into
        results.parquet. A trial interrupted by Ctrl-C, or left running by a worker that died, is
        not listed unless its job wrote a record other than the crash record of a job Ctrl-C
        stopped (:func:`_stopped`): a resumed study asks for a new trial in its place, and its
        unwritten record is not a failed job of the study."""
        # optional dependency: pip install '.[optuna]'
        from optuna.trial import TrialState

        jobs: list[dict[str, Any]] = []
        for t in study.get_trials(deepcopy=False):
            abandoned = t.user_attrs.get("interrupted") or (
                t.state == TrialState.RUNNING and not _alive(*(t.user_attrs.get("worker") or [None, None])[:2])
            )
            for key in t.user_attrs.get("jobs", []) or []:
                if abandoned and (not (sweep_dir / key / RECORD_NAME).is_file() or _stopped(_read(sweep_dir / key))):
                    continue
                jobs.append(
                    {
                        "key": key,
                        "overrides": list(t.user_attrs.get("overrides", [])),
                        "trial": t.number,
                        "skipped": False,
                    }
                )
        info = {
            "started": started,
            "experiments": [],
            "total": len(jobs),
            "to_run": len(jobs),
            "max_attempts": self.max_attempts,
            "study": {"name": study.study_name, "storage": shown_url(url), "n_trials": self.n_trials},
            "jobs": jobs,
        }
        atomic_write(sweep_dir / "sweep.json", dumps_strict(info, indent=1))

    # -- the sweep ------------------------------------------------------------------------------

    def sweep(self, arguments: list[str]) -> Any:
        assert self.config is not None and self.launcher is not None
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        try:
            return self._study(sweep_dir, arguments)
        except (StorageError, OutputError) as exc:
            print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(2 if isinstance(exc, StorageError) else 1) from None

    def _study(self, sweep_dir: Path, arguments: list[str]) -> Any:
        optuna = _import_optuna()
        names, directions = self._objectives()
        study_name = self.study_name if self.study_name is not None else sweep_dir.name
        url = storage_url(self.storage, sweep_dir, study_name)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(sweep_dir / "multirun.yaml", OmegaConf.to_yaml(self.config))
        dims, fixed = self._space([f"{k}={v}" for k, v in self.params.items()] + list(arguments))
        study = self._open_study(optuna, study_name, url, directions)
        started = time.time()
        running: list[tuple[Any, list[tuple[str, list[str]]]]] = []  # the batch in flight, for an interrupt
        batch = _Batch(sweep_dir, started, url, dims, fixed, names)
        # Ctrl-C is recorded and raised where the study can end cleanly: before each batch and
        # each trial's composition, in the launcher's checks and waits; never lost (ctrlc)
        with ctrlc.guarded():
            try:
                self._check_objectives(sweep_dir, names, dims, fixed)
                done_before = self._counted(study)
                to_run = max(0, self.n_trials - done_before)
                print(
                    f"nirspi-run: study {study_name!r} in {shown_url(url)}: {done_before} of {self.n_trials} "
                    f"trials finished or running, {to_run} to run"
                    + (f", {self.repeats} repeats each (median)" if self.repeats > 1 else ""),
                    flush=True,
                )
                self._write_sweep_file(sweep_dir, study, started, url)
                while (room := self.n_trials - self._counted(study)) > 0:
                    ctrlc.check()
                    self._run_batch(study, batch, room, running)
                ctrlc.check()
            except KeyboardInterrupt:
                self._interrupted(study, running, names, sweep_dir, url)
            self._write_sweep_file(sweep_dir, study, started, url)
            self._write_results(study, sweep_dir, len(names))
        return []

    def _objectives(self) -> tuple[list[str], list[str]]:
        """The objective's record keys and their directions; without an objective, exits (2)."""
        names = objective_names(self.config.get("objective"))
        raw_direction = (
            OmegaConf.to_container(self.direction) if OmegaConf.is_config(self.direction) else self.direction
        )
        directions = directions_of(raw_direction, len(names)) if names else []
        if not names:  # the results callback refused it already (sweep_objective); kept for direct use
            print("nirspi-run: error: hydra/sweeper=optuna needs objective=<record key>", file=sys.stderr)
            raise SystemExit(2)
        return names, directions

    def _space(self, params: list[str]) -> tuple[list[Dimension], list[str]]:
        """The search space of the overrides: its dimensions (the last of a name wins) and the
        fixed overrides; one that cannot be sampled exits (2), before anything runs."""
        dims: list[Dimension] = []
        fixed: list[str] = []
        try:
            for text, parsed in zip(params, self._parser().parse_overrides(params), strict=True):
                dim = dimension_of(parsed)
                if dim is None:
                    fixed.append(text)
                else:
                    dims = [d for d in dims if d.name != dim.name] + [dim]
                    fixed = [f for f in fixed if self._parse_one(f).get_key_element() != dim.name]
        except Exception as exc:  # noqa: BLE001 - a space that cannot be sampled: nothing runs
            print(f"nirspi-run: error: the search space cannot be sampled: {str(exc).splitlines()[0]}", file=sys.stderr)
            raise SystemExit(2) from None
        return dims, fixed

    def _open_study(self, optuna: Any, study_name: str, url: str, directions: list[str]) -> Any:
        """The study, created or loaded (a resumed one with its sampler reseeded); a database that
        cannot be opened, or a study with other directions, is a :class:`StorageError`."""
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        logging.getLogger("alembic").setLevel(logging.WARNING)  # "setup plugin ..." lines of a new database
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ExperimentalWarning of multivariate TPE and the like
            try:
                study = optuna.create_study(
                    study_name=study_name,
                    storage=url,
                    sampler=self.sampler,
                    pruner=self.pruner,
                    directions=directions,
                    load_if_exists=True,
                )
            except Exception as exc:  # noqa: BLE001 - a database that cannot be opened: one line
                why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise StorageError(f"hydra.sweeper.storage: cannot open the study in {shown_url(url)}: {why}") from None
            n_before = len(study.get_trials(deepcopy=False))
            sampler = self._sampler_for_resume(n_before)
            if sampler is not None:  # a seeded sampler would replay its first draws: seed + trials so far
                study = optuna.load_study(study_name=study_name, storage=url, sampler=sampler, pruner=self.pruner)
        told = [d.name.lower() for d in study.directions]
        if told != directions:
            raise StorageError(
                f"hydra.sweeper.direction={directions} differs from the study {study_name!r} in {shown_url(url)} "
                f"({told}); allowed: the study's directions, or another study_name / hydra.sweep.dir"
            )
        return study

    def _ask_trials(
        self, study: Any, batch: _Batch, room: int, running: list[tuple[Any, list[tuple[str, list[str]]]]]
    ) -> list[list[str]]:
        """Asks up to ``n_jobs`` trials (at most ``room``), appended to ``running``; their overrides."""
        trial_ov: list[list[str]] = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for i in range(min(self.n_jobs, room)):
                # recounted before each ask: other workers on this study ask too
                if i and self._counted(study) >= self.n_trials:
                    break
                trial = study.ask()
                running.append((trial, []))  # from its ask on: told, or marked interrupted, on Ctrl-C
                values = [d.suggest(trial) for d in batch.dims]
                ov = [
                    *batch.fixed,
                    *(f"{d.name}={as_override_value(v)}" for d, v in zip(batch.dims, values, strict=True)),
                ]
                trial.set_user_attr("overrides", ov)
                trial.set_user_attr("worker", [_HOST, os.getpid()])
                trial_ov.append(ov)
        return trial_ov

    def _run_batch(
        self, study: Any, batch: _Batch, room: int, running: list[tuple[Any, list[tuple[str, list[str]]]]]
    ) -> None:
        """Asks a batch of trials (kept in ``running`` while in flight), runs their jobs, tells them."""
        running.clear()
        trial_ov = self._ask_trials(study, batch, room, running)
        sweep_dir = batch.sweep_dir
        jobs, composed, errors = self._prepare_trials(sweep_dir, trial_ov)
        for i, (trial, _) in enumerate(running):
            trial.set_user_attr("jobs", [k for k, _ in jobs[i]])
            running[i] = (trial, jobs[i])
        self._write_sweep_file(sweep_dir, study, batch.started, batch.url)
        # each folder once: trials asked together may share a configuration, and two runs of
        # one folder at once clobber each other's record (the sweeping process holds both locks)
        unique = list({key: (key, ov) for js in jobs for key, ov in js}.values())
        self._run_jobs(sweep_dir, sweep_dir / "sweep.json", unique, composed)
        for (trial, trial_jobs), error in zip(running, errors, strict=True):
            self._tell(study, trial, trial_jobs, batch.names, sweep_dir, error)
        running.clear()

    def _sampler_for_resume(self, n_before: int) -> Any:
        """For a study that already holds trials, the configured sampler with ``seed`` + the number
        of those trials (reproducible, and not the first run's draws again); None when the study is
        new or the sampler has no seed."""
        # start-up: Hydra's instantiate, only to reseed a resumed study's sampler
        from hydra.utils import instantiate

        node = self.config.hydra.sweeper.get("sampler") if self.config is not None else None
        seed = node.get("seed") if node is not None else None
        if n_before == 0 or node is None or isinstance(seed, bool) or not isinstance(seed, int):
            return None
        return instantiate(node, seed=seed + n_before)

    def _counted(self, study: Any) -> int:
        """Trials toward ``n_trials``: finished (not interrupted), or running in a live worker."""
        # optional dependency: pip install '.[optuna]'
        from optuna.trial import TrialState

        n = 0
        for t in study.get_trials(deepcopy=False):
            if t.state == TrialState.RUNNING:
                host, pid = (t.user_attrs.get("worker") or [None, None])[:2]
                n += _alive(host, pid)
            elif t.state in (TrialState.COMPLETE, TrialState.PRUNED) or (
                t.state == TrialState.FAIL and not t.user_attrs.get("interrupted")
            ):
                n += 1
        return n

    def _tell(
        self,
        study: Any,
        trial: Any,
        jobs: list[tuple[str, list[str]]],
        names: list[str],
        sweep_dir: Path,
        error: str | None,
    ) -> None:
        # optional dependency: pip install '.[optuna]'
        from optuna.trial import TrialState

        records = [_read(sweep_dir / key) for key, _ in jobs]
        values = None if error is not None else median_values(records, names)
        if values is None:
            reason = error or next(
                (str((r or {}).get("meta", {}).get("error") or "") for r in records if r is not None), ""
            )
            trial.set_user_attr("failed", (reason or "a value of the objective is missing")[:300])
            study.tell(trial, state=TrialState.FAIL)
        else:
            study.tell(trial, values if len(values) > 1 else values[0])

    def _check_objectives(self, sweep_dir: Path, names: list[str], dims: list[Dimension], fixed: list[str]) -> None:
        """Refuse (exit 2, one line) an objective the records of this sweep do not have, checked on
        one job's record: the space's first configuration, run once into its keyed folder (a
        trial that asks for it reuses that record). A failing probe job checks nothing."""
        probe = [*fixed, *(f"{d.name}={as_override_value(d.first())}" for d in dims)]
        jobs, composed, errors = self._prepare_trials(sweep_dir, [probe])
        if errors[0] is not None or not jobs[0]:
            return
        key, ov = jobs[0][0]
        record = _read(sweep_dir / key)
        if record is None or (record.get("meta") or {}).get("status") != "ok":
            print("nirspi-run: checking objective on one job's record before the first trial", flush=True)
            self._run_jobs(sweep_dir, sweep_dir / "sweep.json", [(key, ov)], composed)
            record = _read(sweep_dir / key)
        if record is None or (record.get("meta") or {}).get("status") != "ok":
            return
        problem = check_objective_keys(names, record)
        if problem is not None:
            print(f"nirspi-run: error: {problem}", file=sys.stderr, flush=True)
            raise SystemExit(2)

    def _interrupted(
        self,
        study: Any,
        running: list[tuple[Any, list[tuple[str, list[str]]]]],
        names: list[str],
        sweep_dir: Path,
        url: str,
    ) -> None:
        """Ctrl-C: tell Optuna the trials whose jobs finished, mark the rest interrupted (not
        counted, so a rerun runs them again), write the results and say how to resume. A job
        that Ctrl-C stopped (:func:`_stopped`) did not finish."""
        # optional dependency: pip install '.[optuna]'
        from optuna.trial import TrialState

        still = {t.number for t in study.get_trials(deepcopy=False) if t.state == TrialState.RUNNING}
        for trial, jobs in running:
            if trial.number not in still:  # told already
                continue
            records = [_read(sweep_dir / key) for key, _ in jobs]
            if jobs and all(r is not None and not _stopped(r) for r in records):
                self._tell(study, trial, jobs, names, sweep_dir, None)
            else:
                trial.set_user_attr("interrupted", True)
                study.tell(trial, state=TrialState.FAIL)
        trials = study.get_trials(deepcopy=False)
        finished = sum(t.state == TrialState.COMPLETE for t in trials)
        failed = sum(t.state == TrialState.FAIL and not t.user_attrs.get("interrupted") for t in trials)
        self._write_sweep_file(sweep_dir, study, time.time(), url)
        self._end_as_hydra_does()
        print(
            f"nirspi-run: interrupted: {finished} trials finished ok and {failed} failed of {self.n_trials} "
            f"(study {study.study_name!r} in {shown_url(url)}; results in {sweep_dir / 'results.parquet'}); "
            f"resume: {self._resume_command(sweep_dir)}",
            file=sys.stderr,
            flush=True,
        )
        raise SystemExit(130)

    def _end_as_hydra_does(self) -> None:
        """Run the sweep's callbacks' ``on_multirun_end`` (nirspi-pipe's ``collect``: results.parquet,
        front.png, the status line), as Hydra does after a sweep that returns; its exit code is
        dropped (the sweep exits 130). Instantiated from the config (``hydra.callbacks``, which the
        allow-list keeps to nirspi-pipe's own): no import of the results module here, which imports
        this one's plugin package."""
        # start-up: Hydra's instantiate, only on Ctrl-C
        from hydra.utils import instantiate

        for node in (self.config.hydra.get("callbacks") or {}).values():
            try:
                instantiate(node).on_multirun_end(config=self.config)
            except SystemExit:
                pass
            except Exception as exc:  # noqa: BLE001 - the interrupted line still says where the study is
                log.warning("after Ctrl-C, a callback failed: %s", str(exc).splitlines()[0] if str(exc) else exc)

    def _write_results(self, study: Any, sweep_dir: Path, n_objectives: int) -> None:
        """``optimization_results.yaml`` as hydra-optuna-sweeper writes it: the best trial's
        params and value (one objective), or the Pareto solutions (several)."""
        # optional dependency: pip install '.[optuna]'
        from optuna.trial import TrialState

        complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
        if not complete:
            return
        out: dict[str, Any]
        if n_objectives == 1:
            best = study.best_trial
            out = {"name": "optuna", "best_params": best.params, "best_value": best.value}
        else:
            out = {"name": "optuna", "solutions": [{"params": t.params, "values": t.values} for t in study.best_trials]}
        atomic_write(sweep_dir / "optimization_results.yaml", yaml.safe_dump(out, sort_keys=False))
