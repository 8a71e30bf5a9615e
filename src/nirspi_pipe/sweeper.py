"""The ``nirspi`` sweeper: Hydra's basic grid sweeper made resumable, keyed and observable.

It expands the sweep exactly like Hydra's ``basic`` sweeper (command-line sweeps plus
``hydra.sweeper.params``), then for every job:

* composes its config and keys its output folder by :func:`nirspi_pipe.records.config_hash`
  of the resolved config (``hydra.sweep.subdir=<hash>``), so the same job always lands in the
  same folder whatever its position in the sweep;
* skips the job when that folder already holds a complete record (``status == "ok"``), so
  rerunning a sweep command recomputes only what is missing or failed;
* writes ``sweep.json`` in the sweep folder (start time, totals, every job's key and
  overrides), from which a watcher thread prints progress and an ETA as records appear, and which
  :func:`nirspi_pipe.results.collect` uses to list jobs that never wrote a record.

Jobs that composed badly are not launched; they are recorded as failed with the error.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any
from collections.abc import Sequence

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf

from nirspi_pipe.records import RECORD_NAME, config_hash, read_record

__all__ = [
    "NirspiSweeperBase",
    "ProgressWatcher",
    "register_hydra_plugins",
    "SWEEP_FILE",
    "job_key",
    "read_sweep_file",
    "progress_line",
]

log = logging.getLogger(__name__)

SWEEP_FILE = "sweep.json"


def job_key(job_cfg: Any) -> str:
    """The folder key of a composed job config: the hash of its resolved non-hydra part."""
    from omegaconf.errors import InterpolationResolutionError

    plain = OmegaConf.to_container(job_cfg, resolve=False)
    plain.pop("hydra", None)
    try:
        resolved = OmegaConf.to_container(OmegaConf.create(plain), resolve=True)
    except InterpolationResolutionError as exc:
        raise ValueError(
            "a job config interpolates ${hydra:...} outside the hydra node, so it cannot be keyed "
            f"before it runs ({exc.full_key}); for per-job seeds use seed=null"
        ) from None
    return config_hash(resolved)


def subdir_override(key: str) -> str:
    """The override that puts a job in folder ``key``. Quoted: Hydra would read an unquoted hex
    key such as ``4703e54460190101`` as a float (``inf``), and jobs would share a folder."""
    return f"hydra.sweep.subdir='{key}'"


def read_sweep_file(sweep_dir: Path) -> dict[str, Any] | None:
    """``sweep.json`` of a sweep folder, or None when there is none (e.g. a basic sweep)."""
    path = Path(sweep_dir) / SWEEP_FILE
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _record_status(folder: Path) -> str | None:
    try:
        return read_record(folder / RECORD_NAME).get("meta", {}).get("status")
    except (OSError, ValueError):
        return None


def progress_line(sweep_dir: Path) -> str | None:
    """``"7/12 jobs done (1 failed), 3 skipped | elapsed 0:42 | ETA 1:12"`` for a running sweep,
    from ``sweep.json`` and the records written since the sweep started; None without one."""
    info = read_sweep_file(sweep_dir)
    if not info:
        return None
    started = float(info["started"])
    done = failed = 0
    for job in info["jobs"]:
        if job.get("skipped") or job.get("duplicate"):
            continue
        rec = Path(sweep_dir) / job["key"] / RECORD_NAME
        try:
            if rec.stat().st_mtime >= started:
                done += 1
                failed += _record_status(rec.parent) != "ok"
        except OSError:
            continue
    total = int(info["to_run"])
    elapsed = max(0.0, time.time() - started)
    eta = elapsed / done * (total - done) if done else float("nan")

    def hms(s: float) -> str:
        if s != s:  # NaN
            return "?"
        s = int(round(s))
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"

    skipped = sum(bool(j.get("skipped")) and not j.get("duplicate") for j in info["jobs"])
    parts = [f"{done}/{total} jobs done" + (f" ({failed} failed)" if failed else "")]
    if skipped:
        parts[0] += f", {skipped} skipped"
    parts.append(f"elapsed {hms(elapsed)}")
    parts.append(f"ETA {hms(eta)}")
    return " | ".join(parts)


class NirspiSweeperBase(Sweeper):
    """Grid sweeper with config-hash job folders, resume and progress (see module docstring).

    It reuses Hydra's basic sweeper's expansion (``BasicSweeper.split_arguments``) but does not
    subclass it: Hydra's plugin scan re-imports core plugin modules, which breaks ``super()``
    in subclasses of its classes.
    """

    def __init__(self, max_batch_size: int | None = None, params: dict[str, str] | None = None,
                 resume: bool = True, experiments: list[str] | None = None) -> None:
        self.max_batch_size = max_batch_size
        self.params = dict(params or {})
        self.resume = resume
        self.experiments = list(experiments or [])
        self.hydra_context: Any = None
        self.config: Any = None
        self.launcher: Any = None

    def setup(self, *, hydra_context: Any, task_function: Any, config: Any) -> None:
        from hydra.core.plugins import Plugins

        self.hydra_context = hydra_context
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def _grid(self, params: dict[str, str], arguments: list[str]) -> list[list[str]]:
        params_conf = [f"{k}={v}" for k, v in params.items()]
        params_conf.extend(arguments)
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        batches = BasicSweeper.split_arguments(parser.parse_overrides(params_conf), None)
        return [list(job) for batch in batches for job in batch]

    def _expand(self, arguments: list[str]) -> list[list[str]]:
        """Every job's overrides. With ``experiments`` (a meta-experiment such as ``paper``),
        the union of each listed experiment's own grid, each job tagged ``+experiment=<name>``;
        command-line overrides other than the experiment apply to all of them."""
        if not self.experiments:
            return self._grid(self.params, arguments)
        shared = [a for a in arguments if not a.lstrip("+~").startswith("experiment=")]
        loader = self.hydra_context.config_loader
        jobs: list[list[str]] = []
        for name in self.experiments:
            sub = loader.load_sweep_config(self.config, [f"+experiment={name}", *shared])
            params = OmegaConf.to_container(sub.hydra.sweeper.params or {}, resolve=False)
            params = {str(k): str(v) for k, v in params.items()}
            jobs.extend([f"+experiment={name}", *job] for job in self._grid(params, shared))
        return jobs

    def _compose(self, overrides: list[str], bases: dict[tuple[str, ...], Any]) -> Any:
        """A job's composed config, as the launcher will compose it, but fast.

        Hydra composes the defaults list (group choices, ``+``/``~`` overrides) and then
        applies plain ``key=value`` overrides with ``OmegaConf.update(merge=True)``. A full
        composition costs ~0.1 s, so for a grid of N jobs we compose once per distinct set of
        structural overrides (cached in ``bases``) and apply the value overrides to a copy,
        exactly as Hydra does. Anything unusual falls back to Hydra's own composition.
        """
        import copy

        loader = self.hydra_context.config_loader
        repo = getattr(loader, "repository", None)
        try:
            parsed = OverridesParser.create(config_loader=loader).parse_overrides(overrides)
        except Exception:  # noqa: BLE001 - Hydra reports it properly below
            return loader.load_sweep_config(self.config, overrides)
        structural: list[str] = []
        updates: list[Any] = []
        for ov, text in zip(parsed, overrides):
            plain = (
                repo is not None
                and not (ov.is_add() or ov.is_delete() or ov.is_force_add())
                and ov.package is None
                and not ov.key_or_group.startswith("hydra")
                and not repo.group_exists(ov.key_or_group)
            )
            if plain:
                updates.append(ov)
            else:
                structural.append(text)
        base_key = tuple(structural)
        if base_key not in bases:
            bases[base_key] = loader.load_sweep_config(self.config, list(base_key))
        cfg = copy.deepcopy(bases[base_key])
        try:
            for ov in updates:
                OmegaConf.update(cfg, ov.key_or_group, ov.value(), merge=True)
        except Exception:  # noqa: BLE001 - e.g. an unknown key: let Hydra say it
            return loader.load_sweep_config(self.config, overrides)
        return cfg

    def sweep(self, arguments: list[str]) -> Any:
        assert self.config is not None and self.launcher is not None
        assert self.hydra_context is not None
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        loader = self.hydra_context.config_loader

        started = time.time()
        jobs: list[dict[str, Any]] = []
        to_launch: list[list[str]] = []
        seen: set[str] = set()
        bases: dict[tuple[str, ...], Any] = {}
        for overrides in self._expand(arguments):
            key = job_key(self._compose(overrides, bases))
            skipped = self.resume and _record_status(sweep_dir / key) == "ok"
            job: dict[str, Any] = {"key": key, "overrides": overrides, "skipped": skipped}
            if key in seen:
                job["duplicate"] = True  # identical config (e.g. two experiments share a grid): run once
            elif not skipped:
                # quoted: an unquoted hex key such as 4703e54460190101 parses as a float (inf)
                to_launch.append([*overrides, subdir_override(key)])
            seen.add(key)
            jobs.append(job)
        n_dup = sum(bool(j.get("duplicate")) for j in jobs)
        if n_dup:
            log.warning("%d jobs of this sweep repeat another job's config; each config runs once", n_dup)
        info = {
            "started": started,
            "experiments": self.experiments,
            "total": len(jobs),
            "to_run": len(to_launch),
            "jobs": jobs,
        }
        tmp = sweep_dir / (SWEEP_FILE + ".tmp")
        tmp.write_text(json.dumps(info, indent=1))
        tmp.replace(sweep_dir / SWEEP_FILE)
        n_skip = sum(bool(j["skipped"]) and not j.get("duplicate") for j in jobs)
        print(
            f"nirspi-run: sweep of {len(jobs)} jobs in {sweep_dir}: {len(to_launch)} to run"
            + (f", {n_skip} skipped (already complete)" if n_skip else "")
            + (f", {n_dup} identical to another job (run once)" if n_dup else ""),
            flush=True,
        )
        returns: list[Sequence[Any]] = []
        if not to_launch:
            return returns
        batch_size = self.max_batch_size or len(to_launch)
        watcher = ProgressWatcher(sweep_dir)
        watcher.start()
        try:
            for start in range(0, len(to_launch), batch_size):
                batch = to_launch[start : start + batch_size]
                results = self.launcher.launch(batch, initial_job_idx=start)
                returns.append(results)
        finally:
            watcher.stop()
        return returns


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
        self.report()


def register_hydra_plugins() -> None:
    """Register nirspi-pipe's Hydra plugin classes explicitly.

    Hydra only instantiates sweepers from the ``hydra_plugins`` namespace, which it discovers by
    scanning; that scan misses editable installs (Hydra issue #2359). Registering the class by
    hand makes ``hydra/sweeper=nirspi`` work for every kind of install.
    """
    from hydra.core.plugins import Plugins

    from hydra_plugins.nirspi_pipe_sweeper import NirspiSweeper

    Plugins.instance().register(NirspiSweeper)
