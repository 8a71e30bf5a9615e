"""``nirspi-bench compose``: the sweeper's fast composition against Hydra's own, per shipped experiment.

For every experiment (``experiments/experiment/*.yaml``; ``--experiment`` picks some) it expands
the sweep grid as ``nirspi-run -m +experiment=NAME`` does and prints:

* **jobs**: the grid size, and **sets**: its distinct sets of structural overrides (config
  groups, ``+``/``~``), which the sweeper composes once each;
* **fast ms/job**: the sweeper's composition (:meth:`NirspiSweeperBase._compose`: one Hydra
  composition per set, the plain ``key=value`` overrides set on a copy, node references resolved)
  over the whole grid, serially, divided by the jobs; **fallbacks**: the jobs it composed through
  Hydra in full instead (an override it does not apply itself);
* **hydra ms/job**: Hydra's public ``hydra.compose("config", overrides=job)`` followed by
  ``OmegaConf.to_container(resolve=True)``, over ``--sample`` jobs spread over the grid, and what
  the grid would take composed that way (**hydra s/grid**).

``--check-all`` composes every job of every selected grid both ways and compares the resolved
configs (``hydra`` node excluded), the config-group choices and the task overrides, types
included (``5`` is not ``5.0``); it prints the count of jobs checked and every mismatch, and
exits 1 on any. ``tests/test_sweeper_equivalence.py`` runs the same comparison on jobs that
hypothesis draws from every grid. The helpers here (:func:`sweeper_for`, :func:`hydra_job`,
:func:`fast_job`, :func:`difference`) are what that test uses.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from importlib import resources
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

__all__ = ["difference", "experiments", "fast_job", "hydra_job", "hydra_session", "main", "sweeper_for", "typed"]


def experiments() -> list[str]:
    """The shipped experiments (``experiments/experiment/*.yaml``) that the nirspi grid sweeper
    runs, sorted: an experiment for Optuna's sweeper (it sets ``hydra.sweeper.n_trials``, e.g.
    ``pareto_search``) is searched, not gridded, so it has no grid to compose."""
    import yaml  # start-up: only the benchmark and its tests read the experiment files

    folder = Path(str(resources.files("nirspi_pipe.experiments"))) / "experiment"
    names = []
    for path in folder.glob("*.yaml"):
        sweeper = ((yaml.safe_load(path.read_text()) or {}).get("hydra") or {}).get("sweeper") or {}
        if "n_trials" not in sweeper:
            names.append(path.stem)
    return sorted(names)


@contextmanager
def hydra_session() -> Iterator[Any]:
    """Hydra initialised on ``nirspi_pipe.conf`` (public API); yields its config loader."""
    from hydra import initialize_config_module  # start-up: loads hydra and omegaconf (501 ms here)
    from hydra.core.global_hydra import GlobalHydra  # start-up: loads hydra and omegaconf (522 ms here)

    with initialize_config_module(config_module="nirspi_pipe.conf", version_base="1.3"):
        yield GlobalHydra.instance().config_loader()


def sweeper_for(loader: Any, experiment: str, arguments: Sequence[str] = ()) -> Any:
    """The nirspi sweeper of ``nirspi-run -m +experiment=EXPERIMENT ARGUMENTS``, set up for keying
    (its sweep config composed by Hydra, its ``hydra.sweeper`` settings, the config loader)."""
    from hydra.types import RunMode  # start-up: loads hydra and omegaconf (495 ms here)
    from omegaconf import OmegaConf  # start-up: loads omegaconf (227 ms here)

    from nirspi_pipe.app.sweeper import NirspiSweeperBase  # start-up: loads hydra and omegaconf (656 ms here)

    cfg = loader.load_configuration("config", [f"+experiment={experiment}", *arguments], run_mode=RunMode.MULTIRUN)
    node = cast("dict[str, Any]", OmegaConf.to_container(cfg.hydra.sweeper, resolve=False))
    node.pop("_target_", None)
    sweeper = NirspiSweeperBase(**node)
    sweeper.hydra_context = SimpleNamespace(config_loader=loader)  # all that keying uses of it
    sweeper.config = cfg
    return sweeper


def hydra_job(overrides: Sequence[str]) -> Any:
    """A job as Hydra's public ``compose`` makes it: a :class:`~nirspi_pipe.app.jobcomposer.ComposedJob`
    (the config resolved by OmegaConf without the ``hydra`` node, the group choices without
    ``hydra/*``, ``hydra.overrides.task``), or the exception composing or resolving raised.
    Call it inside :func:`hydra_session`."""
    from hydra import compose  # start-up: loads hydra and omegaconf (501 ms here)
    from omegaconf import OmegaConf, open_dict, read_write  # start-up: loads omegaconf (227 ms here)

    from nirspi_pipe.app.jobcomposer import ComposedJob  # start-up: loads hydra and omegaconf (656 ms here)

    try:
        cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
        choices = {str(k): v for k, v in cfg.hydra.runtime.choices.items() if not str(k).startswith("hydra/")}
        task = [str(t) for t in cfg.hydra.overrides.task]
        with read_write(cfg), open_dict(cfg):
            del cfg["hydra"]  # as compose(return_hydra_config=False) does
        config = cast("dict[str, Any]", OmegaConf.to_container(cfg, resolve=True))
    except Exception as exc:  # noqa: BLE001 - a job that does not compose is compared as such
        return exc
    return ComposedJob(config, choices, task)


def fast_job(sweeper: Any, overrides: Sequence[str], bases: dict[Any, Any]) -> Any:
    """A job as the sweeper composes it to key and run it (``bases``: its cache of composed
    structural override sets, shared by the jobs of a sweep), or the exception it raised."""
    try:
        return sweeper._compose(list(overrides), bases)
    except Exception as exc:  # noqa: BLE001 - compared as such
        return exc


def typed(value: Any) -> Any:
    """``value`` with every scalar paired with its type name, so that ``5 != 5.0 != True``."""
    if isinstance(value, dict):
        return {k: typed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [typed(v) for v in value]
    return (type(value).__name__, value)


def _first_difference(a: Any, b: Any, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                return f"{path}{k}: only in {'hydra' if k in b else 'sweeper'}"
            found = _first_difference(a[k], b[k], f"{path}{k}.")
            if found:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            found = _first_difference(x, y, f"{path}{i}.")
            if found:
                return found
        return None
    if typed(a) != typed(b):
        return f"{path.rstrip('.')}: sweeper {a!r}, hydra {b!r}"
    return None


def difference(fast: Any, hydra: Any) -> str | None:
    """None when the sweeper's job and Hydra's agree (both compose to the same resolved config,
    choices and task overrides, types included, or both fail); else the first difference."""
    if isinstance(fast, BaseException) or isinstance(hydra, BaseException):
        if isinstance(fast, BaseException) and isinstance(hydra, BaseException):
            return None
        which, exc = ("sweeper", fast) if isinstance(fast, BaseException) else ("hydra", hydra)
        first = str(exc).strip().splitlines()
        return f"only {which} fails: {type(exc).__name__}: {first[0] if first else ''}"
    for part in ("config", "choices", "task_overrides"):
        found = _first_difference(getattr(fast, part), getattr(hydra, part))
        if found:
            return f"{part}: {found}"
    return None


def _measure(loader: Any, name: str, sample: int, check_all: bool) -> tuple[list[str], int]:
    sweeper = sweeper_for(loader, name)
    grid = sweeper._expand([f"+experiment={name}"])
    fallbacks = 0
    full = sweeper._composed

    def counted(overrides: list[str]) -> Any:
        nonlocal fallbacks
        fallbacks += 1
        return full(overrides)

    sweeper._composed = counted
    bases: dict[Any, Any] = {}
    t0 = time.perf_counter()
    for job in grid:
        fast_job(sweeper, job, bases)
    fast_s = time.perf_counter() - t0
    picks = [grid[round(i * (len(grid) - 1) / max(sample - 1, 1))] for i in range(min(sample, len(grid)))]
    t0 = time.perf_counter()
    for job in picks:
        hydra_job(job)
    hydra_s = (time.perf_counter() - t0) / len(picks)
    line = (
        f"{name:<15} {len(grid):>6} {len(bases):>5} {1e3 * fast_s / len(grid):>12.2f} {fallbacks:>9}"
        f" {1e3 * hydra_s:>12.1f} {hydra_s * len(grid):>12.1f} {hydra_s * len(grid) / fast_s:>7.0f}"
    )
    mismatches: list[str] = []
    if check_all:
        bases = {}
        for job in grid:
            found = difference(fast_job(sweeper, job, bases), hydra_job(job))
            if found:
                mismatches.append(f"{name}: {' '.join(job)}: {found}")
                print(f"MISMATCH {mismatches[-1]}", flush=True)
        line += f" {len(mismatches):>10}"
    print(line, flush=True)
    return mismatches, len(grid)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench compose", description=__doc__)
    parser.add_argument("--experiment", action="append", help="an experiment (repeatable; default: every one)")
    parser.add_argument("--sample", type=int, default=10, help="jobs per grid composed through Hydra to time it")
    parser.add_argument("--check-all", action="store_true", help="compare every job of every grid with Hydra's")
    ns = parser.parse_args(argv)
    shipped = experiments()
    for name in ns.experiment or ():  # a shipped experiment's name, never a path (issue 41)
        if name not in shipped:
            parser.error(f"--experiment {name[:80]!r} is not a shipped experiment; allowed: {', '.join(shipped)}")
    if ns.sample < 1:
        parser.error(f"--sample {ns.sample} is not allowed; allowed: an integer >= 1")
    names = ns.experiment or shipped
    print(
        f"{'experiment':<15} {'jobs':>6} {'sets':>5} {'fast ms/job':>12} {'fallbacks':>9}"
        f" {'hydra ms/job':>12} {'hydra s/grid':>12} {'ratio':>7}" + (f" {'mismatches':>10}" if ns.check_all else "")
    )
    mismatches: list[str] = []
    checked = 0
    t0 = time.perf_counter()
    with hydra_session() as loader:
        for name in names:
            found, n = _measure(loader, name, max(ns.sample, 1), ns.check_all)
            mismatches.extend(found)
            checked += n
    if ns.check_all:
        print(
            f"checked {checked} jobs of {len(names)} experiments against hydra.compose:"
            f" {len(mismatches)} mismatches ({time.perf_counter() - t0:.0f} s)"
        )
    return 1 if mismatches else 0
