"""The jobs of a sweep, composed and keyed (:mod:`nirspi_pipe.app.sweeper`): the grid as Hydra's
basic sweeper expands it (:func:`expand_grid`), a job's config as the sweeper composed it to key
it and as the ``nirspi`` launcher runs it (:class:`ComposedJob`), its folder key
(:func:`job_key`, :func:`nirspi_pipe.jobkey.job_key_of`) and the override that puts it there
(:func:`subdir_override`); plain value overrides set on a composed base as Hydra sets them
(:func:`set_plain`, :func:`resolve_plain`); why a job did not compose or was refused.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

from omegaconf import OmegaConf
from omegaconf.errors import InterpolationResolutionError

from nirspi_pipe.jobkey import InputHasher, job_key_of

__all__ = [
    "ComposeFailure",
    "ComposedJob",
    "JobRefused",
    "choices_of",
    "composed_job",
    "error_line",
    "error_type",
    "expand_grid",
    "job_key",
    "resolve_plain",
    "set_plain",
    "subdir_override",
]


def _resolved(job_cfg: Any) -> dict[str, Any]:
    plain = cast("dict[str, Any]", OmegaConf.to_container(job_cfg, resolve=False))
    plain.pop("hydra", None)
    return resolve_plain(plain)


#: An interpolation that is a whole-value reference to another node: ``${fog}``, ``${a.b}``.
_NODE_REF = re.compile(r"^\$\{([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)\}$")
#: A whole-value ``oc.select`` of an absolute key with the default ``null``:
#: ``${oc.select:scene.distance_mm,null}`` (conf/fusion/itof.yaml).
_SELECT_OR_NULL = re.compile(r"^\$\{oc\.select:\s*([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)\s*,\s*null\s*\}$")


class _NotSimple(Exception):
    """The config holds an interpolation other than a plain node reference."""


def _resolve_references(root: dict[str, Any]) -> dict[str, Any]:
    """``OmegaConf.to_container(OmegaConf.create(root), resolve=True)`` for a config whose only
    interpolations are whole-value references to other nodes (``source.effects.fog: ${fog}``) and
    whole-value ``${oc.select:abs.key,null}`` (all that the shipped configs use): each becomes a
    copy of the node it names, resolved in turn; an ``oc.select`` whose key is absent (its parents
    being mappings) or ``???`` becomes None, as OmegaConf's ``select_value`` gives its default.
    Raises :class:`_NotSimple` for anything else (other resolvers or defaults, string
    interpolation, relative or missing keys, cycles), which OmegaConf then resolves. Before, the per-job
    part of keying (all but the 50 compositions) took 24 of the paper sweep's 55 s of keying under
    ``cProfile``, most of it in OmegaConf; then the 1280 3D jobs (``fusion=itof``'s ``oc.select``)
    still went through OmegaConf: 240 of 417 s of keying under ``cProfile``.
    ``tests/test_sweeper.py`` compares the keys with Hydra's own composition,
    ``tests/test_job_overhead.py`` this function with OmegaConf."""

    def lookup(path: str, depth: int, default_none: bool = False) -> Any:
        node: Any = root
        for part in path.split("."):
            if not isinstance(node, dict):
                raise _NotSimple(path)
            if part not in node:
                if default_none:
                    return None
                raise _NotSimple(path)
            node = node[part]
        if default_none and node == "???":
            return None  # a missing value: select_value gives the default
        return resolve(node, depth + 1)

    def resolve(node: Any, depth: int) -> Any:
        if depth > 32:
            raise _NotSimple("reference cycle")
        if isinstance(node, dict):
            return {k: resolve(v, depth) for k, v in node.items()}
        if isinstance(node, list):
            return [resolve(v, depth) for v in node]
        if isinstance(node, str) and "$" in node:
            ref = _NODE_REF.match(node)
            if ref is not None:
                return lookup(ref.group(1), depth)
            select = _SELECT_OR_NULL.match(node)
            if select is not None:
                return lookup(select.group(1), depth, default_none=True)
            raise _NotSimple(node)
        return node

    return cast("dict[str, Any]", resolve(root, 0))


def resolve_plain(plain: dict[str, Any]) -> dict[str, Any]:
    try:
        return _resolve_references(plain)
    except _NotSimple:
        pass
    try:
        return cast("dict[str, Any]", OmegaConf.to_container(OmegaConf.create(plain), resolve=True))
    except InterpolationResolutionError as exc:
        raise ValueError(
            "a job config interpolates ${hydra:...} outside the hydra node, so it cannot be keyed "
            f"before it runs ({exc.full_key}); for per-job seeds use seed=null"
        ) from None


def choices_of(cfg: Any) -> dict[str, Any]:
    """``hydra.runtime.choices`` of a composed config, ``hydra/*`` groups left out (as records keep them)."""
    return {str(k): v for k, v in cfg.hydra.runtime.choices.items() if not str(k).startswith("hydra/")}


def set_plain(cfg: dict[str, Any], dotted: str, value: Any) -> bool:
    """Set ``dotted`` (``scene.distance_mm``) in a plain config as Hydra's ``OmegaConf.update(...,
    merge=True)`` of a struct config would: only an existing key, only a non-mapping value over a
    non-mapping one. False (nothing set) for anything else, which the caller composes in full.

    ``cfg`` itself is changed, but every mapping below it on the way to ``dotted`` is copied
    first (copy on write), so the rest may be shared with the sweeper's composed base: a
    shallow copy of the base per job instead of a deep one (``copy.deepcopy`` was 3 % of the
    paper sweep's keying under ``cProfile``; issue 42 item 6)."""
    node: Any = cfg
    *parents, leaf = dotted.split(".")
    for part in parents:
        child = node.get(part)
        if not isinstance(child, dict):  # absent, or a value: Hydra's update would not set below it
            return False
        node[part] = node = dict(child)
    if not isinstance(node, dict) or leaf not in node or isinstance(node[leaf], dict) or isinstance(value, dict):
        return False
    node[leaf] = value
    return True


@dataclass(frozen=True)
class ComposedJob:
    """A job as the sweeper composed it to key it, and as the ``nirspi`` launcher runs it.

    Attributes:
        config: the resolved config without the ``hydra`` node (the task's config).
        choices: the option of every config group (``hydra/*`` groups left out).
        task_overrides: the job's overrides other than ``hydra.*`` (``hydra.overrides.task``).
    """

    config: dict[str, Any]
    choices: dict[str, Any]
    task_overrides: list[str]


def composed_job(cfg: Any) -> ComposedJob:
    """The :class:`ComposedJob` of a config Hydra composed (``load_sweep_config``)."""
    task = list(OmegaConf.to_container(cfg.hydra.overrides.task, resolve=False) or [])
    return ComposedJob(_resolved(cfg), choices_of(cfg), task)


def job_key(job_cfg: Any, hasher: InputHasher | None = None) -> str:
    """The folder key of a composed job config: the hash of its resolved non-hydra part and of
    the content of every input file it names (:func:`nirspi_pipe.jobkey.job_key_of`)."""
    resolved = _resolved(job_cfg)
    return job_key_of(resolved, (hasher or InputHasher()).hashes(resolved))


class JobRefused(ValueError):
    """A job whose composed Hydra node the job gate refuses (:func:`nirspi_pipe.app.hydranode.check_job`);
    one line. Raised, not recorded: every job of the sweep would receive the same node, so the sweep
    stops (exit 2). Picklable, so that a forked keying worker hands it back to the sweeping process
    instead of dying with ``SystemExit`` (the pool then waited forever for the lost task)."""


class ComposeFailure(Exception):
    """Why a job did not compose, as a keying worker process reports it (picklable, whatever
    the original exception): ``type_name`` is the original exception's class name."""

    def __init__(self, type_name: str, message: str) -> None:
        super().__init__(message)
        self.type_name = type_name

    def __reduce__(self) -> tuple[Any, ...]:
        return (ComposeFailure, (self.type_name, str(self)))


def error_type(exc: BaseException) -> str:
    return exc.type_name if isinstance(exc, ComposeFailure) else type(exc).__name__


def subdir_override(key: str) -> str:
    """The override that puts a job in folder ``key``. Quoted: Hydra would read an unquoted hex
    key such as ``4703e54460190101`` as a float (``inf``), and jobs would share a folder."""
    return f"hydra.sweep.subdir='{key}'"


def expand_grid(overrides: Sequence[Any]) -> list[list[str]]:
    """Every job of a grid, as Hydra's basic sweeper expands it: the cartesian product of each
    sweep override's values (in order), plain overrides kept as they are; a key given twice (an
    experiment's ``seed: range(0,20)`` and ``seed=0,1`` on the command line) takes its last value,
    where it first appeared. ``overrides`` are parsed
    :class:`hydra.core.override_parser.types.Override` objects (Hydra's public parser)."""
    lists: dict[str, list[str]] = {}  # a later override of the same key replaces the earlier (Hydra's rule)
    for ov in overrides:
        key = ov.get_key_element()
        if ov.is_sweep_override():
            if not ov.is_discrete_sweep():
                raise ValueError(
                    f"{key}: the nirspi sweeper takes lists, range() and choice(); not interval() ({ov.input_line})"
                )
            lists[key] = [f"{key}={val}" for val in ov.sweep_string_iterator()]
        else:
            lists[key] = [f"{key}={ov.get_value_element_as_str()}"]
    return [list(job) for job in itertools.product(*lists.values())]


def error_line(text: str) -> str:
    """Hydra's multi-line composition errors as one line (with the allowed options, if listed)."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    if not lines:
        return "unknown error"
    head, allowed = lines[0], []
    for ln in lines[1:]:
        if ln.startswith("Config search path"):
            break
        if not ln.startswith("Available options") and not ln.startswith("To append"):
            allowed.append(ln)
    return head + (f"; allowed: {', '.join(allowed)}" if allowed and "Available" in text else "")
