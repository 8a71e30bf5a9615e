"""The one checked entry path to Hydra (issue 32): ``nirspi-run`` (every flag and ``-m``) and the
Python API reach Hydra only through :func:`check_invocation`, which fails closed.

1. **Flags are matched exactly** against :data:`FLAGS` before anything else. Anything that starts
   with ``-`` and is not spelled exactly as there (an abbreviation argparse would expand,
   ``--experimental-rerun``, ``--run``, ``--``) is refused with one line. Hydra then gets the
   canonical spelling (``--cfg=job``), so argparse has nothing left to expand.
2. ``-cd DIR`` becomes a ``hydra.searchpath`` override, so the check and Hydra use the same
   search path *by construction*: Hydra never sees ``-cd``.
3. **The composed configuration is checked**, Hydra's node included, with Hydra's public compose
   API, the same config name and the same overrides Hydra gets. A configuration that does not
   compose is refused (one line), never handed on.
4. **Hydra's node is compared** with the one composed without the user's overrides, config
   folder or config name (only the ``hydra/…`` choices kept); a difference outside the allow-list
   of :mod:`nirspi_pipe.app.allowlist` is refused. The job part is checked as before
   (:mod:`nirspi_pipe.app.validate`: allowed targets, known keys, types).
5. **Sweeps**: each swept value (command line and ``hydra.sweeper.params``) is checked for its
   key; a sweep that cannot be enumerated (Optuna's ``interval(a,b)``) by its bounds. A swept
   config group whose options may come from a user's folder (``-cd``, a ``hydra.searchpath``
   entry) is composed once per value and checked in full.

Refusals raise :class:`Refused` (one line; ``nirspi-run`` prints it with exit 2, the API raises
:class:`~nirspi_pipe.app.api.BadOverrides`).
"""

from __future__ import annotations

import itertools
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.object_type import ObjectType
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Glob, IntervalSweep
from hydra.types import RunMode
from omegaconf import OmegaConf
from omegaconf.errors import InterpolationKeyError, InterpolationResolutionError

from nirspi_pipe.app import allowlist
from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME, all_groups, group_options
from nirspi_pipe.errors import ConfigError, yaml_problem
from nirspi_pipe.safeio import short_repr
from nirspi_pipe.targets import check_target, check_targets

__all__ = ["FLAGS", "REFUSED_FLAGS", "Invocation", "Refused", "check_invocation", "parse_args", "check_hydra_node"]


class Refused(ValueError):
    """An invocation the entry check refuses; the message is one line naming the flag or key."""


#: Every flag ``nirspi-run`` accepts, exactly as spelled: ``{spelling: (canonical, value)}``;
#: ``value`` is None (a switch), ``"any"`` (one value), a tuple of allowed values, or
#: ``("?", choices)`` (an optional value, ``--info``). ``--version`` and ``--plugins`` are ours.
FLAGS: dict[str, tuple[str, Any]] = {
    "-h": ("--help", None),
    "--help": ("--help", None),
    "--hydra-help": ("--hydra-help", None),
    "--version": ("--version", None),
    "--plugins": ("--plugins", None),
    "-c": ("--cfg", ("job", "hydra", "all")),
    "--cfg": ("--cfg", ("job", "hydra", "all")),
    "--resolve": ("--resolve", None),
    "-p": ("--package", "any"),
    "--package": ("--package", "any"),
    "-m": ("--multirun", None),
    "--multirun": ("--multirun", None),
    "-i": ("--info", ("?", ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath"))),
    "--info": ("--info", ("?", ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath"))),
    "-sc": ("--shell-completion", None),
    "--shell-completion": ("--shell-completion", None),
    "-cd": ("--config-dir", "any"),
    "--config-dir": ("--config-dir", "any"),
    "-cn": ("--config-name", "any"),
    "--config-name": ("--config-name", "any"),
}
#: Hydra flags that are refused, with the reason.
REFUSED_FLAGS: dict[str, str] = {
    "--experimental-rerun": "it unpickles a file, and unpickling runs code",
    "-cp": "use -cd/--config-dir (added to the search path) instead",
    "--config-path": "use -cd/--config-dir (added to the search path) instead",
    "-r": "a run is what nirspi-run does without a flag; leave it out",
    "--run": "a run is what nirspi-run does without a flag; leave it out",
}
#: Flags that select what Hydra does; at most one.
_COMMANDS = ("--multirun", "--cfg", "--shell-completion", "--info")
_SHELLS = ("bash", "zsh", "fish")
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}$")
_CONFIG_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*$")
_PACKAGE = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*$")
_WORD = re.compile(r"^[A-Za-z0-9_.:+-]{1,100}$")
_SUBDIR_PART = re.compile(r"^[A-Za-z0-9_.=,+-]+$")
_SUBDIR_INTERPOLATIONS = ("${hydra.job.num}", "${hydra.job.id}", "${hydra.job.name}")


@dataclass(frozen=True)
class Invocation:
    """A checked invocation.

    Attributes:
        flags: canonical flag → value (None for a switch).
        overrides: the overrides as checked and as Hydra gets them (``-cd`` turned into
            ``hydra.searchpath``, ``group=null`` into the group's ``off`` option).
        hydra_argv: what Hydra's argument parser gets: canonical flags, then the overrides.
        config_name: the primary config's name.
        config: the composed configuration that was checked (Hydra's node included).
    """

    flags: dict[str, str | None] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()
    hydra_argv: tuple[str, ...] = ()
    config_name: str = CONFIG_NAME
    config: Any = field(default=None, compare=False, repr=False)

    @property
    def multirun(self) -> bool:
        return "--multirun" in self.flags


def parse_args(args: list[str]) -> tuple[dict[str, str | None], list[str]]:
    """Split ``args`` into canonical flags and overrides; :class:`Refused` for any flag not
    spelled exactly as in :data:`FLAGS`, a flag given twice, or a missing/wrong flag value."""
    flags: dict[str, str | None] = {}
    overrides: list[str] = []
    i = 0
    while i < len(args):
        arg = args[i]
        i += 1
        if not arg.startswith("-"):
            overrides.append(arg)
            continue
        spelled, eq, inline = arg.partition("=")
        canonical, kind = _known_flag(spelled, arg)
        if canonical in flags:
            raise Refused(f"{spelled} is given twice; allowed: once")
        flags[canonical], i = _flag_value(spelled, kind, inline if eq else None, args, i)
    _check_flag_combination(flags)
    return flags, overrides


def _known_flag(spelled: str, arg: str) -> tuple[str, Any]:
    """``(canonical name, value kind)`` of a flag spelled exactly as in :data:`FLAGS`, or
    :class:`Refused`."""
    if spelled in REFUSED_FLAGS:
        raise Refused(f"{spelled} is not allowed: {REFUSED_FLAGS[spelled]}")
    if spelled not in FLAGS:
        raise Refused(
            f"{arg[:60]!r} is not a flag nirspi-run accepts (flags are matched exactly, no abbreviations); "
            f"allowed: {', '.join(sorted(FLAGS))}"
        )
    return FLAGS[spelled]


def _flag_value(spelled: str, kind: Any, inline: str | None, args: list[str], i: int) -> tuple[str | None, int]:
    """The value of flag ``spelled`` (``inline``: after ``=``; else ``args[i]`` when the kind takes
    it) and the position after it; :class:`Refused` for a value it does not allow."""
    if kind is None:  # a switch
        if inline is not None:
            raise Refused(f"{spelled} takes no value; allowed: {spelled} alone")
        return None, i
    if isinstance(kind, tuple) and kind and kind[0] == "?":  # an optional value among choices
        choices = kind[1]
        if inline is not None:
            value = inline
        elif i < len(args) and args[i] in choices:
            value, i = args[i], i + 1
        else:
            value = choices[0]
        if value not in choices:
            raise Refused(f"{spelled}={value!r} is not allowed; allowed: {', '.join(choices)}")
        return value, i
    if inline is not None:  # a required value (free, or among the choices of ``kind``)
        value = inline
    elif i < len(args) and not args[i].startswith("-"):
        value, i = args[i], i + 1
    else:
        raise Refused(f"{spelled} needs a value; allowed: {spelled} VALUE")
    if isinstance(kind, tuple) and value not in kind:
        raise Refused(f"{spelled}={value!r} is not allowed; allowed: {', '.join(kind)}")
    return value, i


def _check_flag_combination(flags: dict[str, str | None]) -> None:
    """:class:`Refused` for flags that cannot go together or a malformed package or config name."""
    commands = [c for c in _COMMANDS if c in flags]
    if len(commands) > 1:
        raise Refused(f"{' and '.join(commands)} cannot be combined; allowed: one of {', '.join(_COMMANDS)}")
    if "--resolve" in flags and not ({"--cfg", "--help"} & set(flags)):
        raise Refused("--resolve is only allowed with --cfg or --help")
    if "--package" in flags and not _PACKAGE.match(str(flags["--package"])):
        raise Refused(f"--package={flags['--package']!r} is not allowed; allowed: a dotted key path (scene, hydra.run)")
    name = flags.get("--config-name")
    if name is not None and (not _CONFIG_NAME.match(name) or ".." in name.split("/")):
        raise Refused(f"--config-name={name!r} is not allowed; allowed: a config name (letters, digits, _ . -)")


def _one_line(text: object, limit: int = 300) -> str:
    return " ".join(str(text).split())[:limit]


# --------------------------------------------------------------------------- composition


def _compose(config_name: str, overrides: list[str]) -> Any:
    """The configuration Hydra will compose (``return_hydra_config``), or :class:`Refused`.

    What Hydra fills itself (``hydra.overrides``, ``hydra.runtime``) is checked to be exactly what
    it fills from ``overrides`` (:func:`check_filled_by_hydra`): Hydra re-applies
    ``hydra.overrides.hydra`` to every sweep job and sweeps ``hydra.overrides.task``, so a list a
    config brings there would run unchecked."""
    user_folder = any(ov.key_or_group == "hydra.searchpath" for ov in _parse(overrides))
    running = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    try:
        if running is not None:  # inside a running app (a job's gate in a worker): set aside, restored below
            GlobalHydra.instance().clear()
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            cfg = compose(config_name, overrides, return_hydra_config=True)
            known = None
            if user_folder:  # a user's file may plant hydra.runtime.choices: compare with Hydra's own
                loader = GlobalHydra.instance().config_loader()
                known = dict(loader.compute_defaults_list(config_name, overrides, RunMode.RUN).overrides.known_choices)
    except Exception as exc:  # noqa: BLE001 - any composition failure is a refusal (fail closed)
        problem = yaml_problem(exc)
        if problem:
            raise Refused(problem) from None
        cause: BaseException = exc
        while cause.__cause__ is not None and not str(cause).strip():
            cause = cause.__cause__
        text = str(cause).strip().splitlines()
        raise Refused(
            f"the configuration does not compose: {_one_line(text[0] if text else type(exc).__name__)}"
        ) from None
    finally:
        if running is not None:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(running)
    check_filled_by_hydra(OmegaConf.to_container(cfg.hydra, resolve=False), overrides, known)  # type: ignore[arg-type]
    return cfg


#: The leaves of ``hydra.runtime`` Hydra sets itself when it composes (the run's ``output_dir``
#: when a job starts).
_RUNTIME_KEYS = frozenset({"version", "version_base", "cwd", "config_sources", "output_dir", "choices"})


def check_filled_by_hydra(
    hydra_node: dict[str, Any], overrides: list[str], known_choices: dict[str, Any] | None = None
) -> None:
    """:class:`Refused` unless ``hydra.overrides`` and ``hydra.runtime`` of a composed node are
    exactly what Hydra fills from ``overrides``: ``overrides.hydra`` the input lines of the Hydra
    overrides, ``overrides.task`` the others, in order; ``runtime`` only Hydra's own keys, its
    ``output_dir`` unset, and (``known_choices``: Hydra's defaults list) no group choice that
    Hydra did not make."""
    parsed = _parse(overrides)
    want = {
        "hydra": [ov.input_line for ov in parsed if ov.is_hydra_override()],
        "task": [ov.input_line for ov in parsed if not ov.is_hydra_override()],
    }
    got = hydra_node.get("overrides") or {}
    if not isinstance(got, dict) or set(got) != set(want) or any(got[k] != want[k] for k in want):
        extra = [str(v) for k in want for v in (got.get(k) or []) if v not in want[k]] if isinstance(got, dict) else []
        shown = f" (it holds {_short(extra[0])})" if extra else ""
        raise Refused(
            f"hydra.overrides differs from the command line{shown}: it is not allowed in a config or an "
            "override; allowed: Hydra fills it from the command line (set each key by its own override)"
        )
    runtime = hydra_node.get("runtime") or {}
    extra_keys = sorted(set(runtime) - _RUNTIME_KEYS) if isinstance(runtime, dict) else ["runtime"]
    if extra_keys or runtime.get("output_dir") != "???":
        key = f"hydra.runtime.{extra_keys[0]}" if extra_keys else "hydra.runtime.output_dir"
        raise Refused(f"{key} is not allowed: Hydra fills hydra.runtime itself; allowed: leave it out")
    if known_choices is not None:
        planted = sorted(set(runtime.get("choices") or {}) - set(known_choices))
        if planted:
            raise Refused(
                f"hydra.runtime.choices.{planted[0]} is not allowed: Hydra fills hydra.runtime itself "
                "(a record would name a choice that was not made); allowed: choose the group (+GROUP=NAME)"
            )


@lru_cache(maxsize=8)
def _baseline(choices: tuple[tuple[str, str | None], ...]) -> dict[str, Any]:
    """Hydra's node composed from the default config and search path, with the given
    ``hydra/…`` choices only (unresolved, as plain containers). Cached per process."""
    overrides = [f"{g}={'null' if o is None else o}" for g, o in choices]
    cfg = _compose(CONFIG_NAME, overrides)
    return OmegaConf.to_container(cfg.hydra, resolve=False)  # type: ignore[return-value]


def _default_choices() -> dict[str, str | None]:
    return dict(_baseline(()).get("runtime", {}).get("choices", {}))


def _hydra_group_options(group: str) -> list[str]:
    """Options of a Hydra group (``hydra/launcher``) on the default search path; also inside a
    running app (a job's gate), whose Hydra is set aside and restored as in :func:`_compose` (the
    gate said "allowed: (none)" there)."""
    running = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    try:
        if running is not None:
            GlobalHydra.instance().clear()
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            return sorted(GlobalHydra.instance().config_loader().get_group_options(group, ObjectType.CONFIG))
    except Exception:  # noqa: BLE001 - only used to name the allowed options
        return []
    finally:
        if running is not None:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(running)


def _primary_exists(name: str) -> bool:
    """Whether ``name`` is a primary config on the default search path (a ``-cd`` folder joins
    Hydra's search path as a ``hydra.searchpath`` entry, after the primary config is chosen)."""
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return bool(GlobalHydra.instance().config_loader().get_sources()) and any(
            src.is_config(name) for src in GlobalHydra.instance().config_loader().get_sources()
        )


def default_searchpath() -> list[str]:
    """``hydra.searchpath`` of the primary config (conf/config.yaml)."""
    return [str(p) for p in _baseline(()).get("searchpath", [])]


# --------------------------------------------------------------------------- Hydra's node


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted key → value for every leaf of a plain tree (lists and empty dicts are leaves)."""
    if isinstance(node, dict) and node:
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: node}


def _match(pattern: str, key: str) -> bool:
    pp, kk = pattern.split("."), key.split(".")
    if pp[-1] == "**":
        return len(kk) >= len(pp) and all(p in ("*", k) for p, k in zip(pp[:-1], kk, strict=False))
    return len(pp) == len(kk) and all(p in ("*", k) for p, k in zip(pp, kk, strict=True))


def _kind_of(key: str) -> str | None:
    for pattern, kind in allowlist.HYDRA_KEYS.items():
        if _match(pattern, key):
            return kind
    return None


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_subdir(value: Any) -> str | None:
    if not isinstance(value, str) or not value:
        return "a relative folder name"
    text = value
    for interp in _SUBDIR_INTERPOLATIONS:
        text = text.replace(interp, "x")
    parts = text.split("/")
    if text.startswith("/") or any(p in ("", ".", "..") or not _SUBDIR_PART.match(p) for p in parts):
        return (
            "a relative folder below the sweep folder: letters, digits and _ . = , + -, no '..', "
            f"interpolations only {', '.join(_SUBDIR_INTERPOLATIONS)}"
        )
    return None


# ----- the kinds of Hydra keys (allowlist.HYDRA_KEYS): each checker returns None when the value
# fits, else the allowed values (for the message). All take (key, value, hydra_node).


def _kind_dir(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    ok = isinstance(value, str) and value.strip() != "" and not any(ord(c) < 32 for c in value)
    return None if ok else "a folder name (a non-empty string)"


def _kind_subdir(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return _check_subdir(value)


def _kind_output_subdir(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if value in (None, ".hydra") else "null or .hydra (Hydra's default)"


def _kind_name(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    ok = isinstance(value, str) and bool(_NAME.match(value)) and value not in (".", "..")
    return None if ok else "a name of letters, digits and _ . - (not a path)"


def _kind_name_or_null(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if value is None else _kind_name(key, value, hydra_node)


def _kind_mode(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    name = getattr(value, "name", value)  # Hydra's RunMode enum once composed
    return None if name in (None, "RUN", "MULTIRUN") else "RUN, MULTIRUN or null"


def _kind_verbose(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    items = value if isinstance(value, list) else [value]
    ok = isinstance(value, bool) or all(isinstance(v, str) and _PACKAGE.match(v) for v in items)
    return None if ok else "true, false, or logger name(s)"


def _kind_bool(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if isinstance(value, bool) else "true or false"


def _kind_int(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if _is_int(value) and value >= 1 else "an integer >= 1"


def _kind_n_jobs(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if _is_int(value) and (value >= 1 or value == -1) else "-1 (one per core) or an integer >= 1"


def _kind_int_or_null(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if value is None or (_is_int(value) and value >= 0) else "an integer >= 0 or null"


def _kind_number_or_null(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if value is None or (_is_number(value) and value > 0) else "a number > 0 or null"


def _kind_fraction(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if _is_number(value) and 0 <= value <= 1 else "a number in [0, 1]"


def _kind_scalar(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    last = key.rsplit(".", 1)[-1]
    if last in allowlist.OPTUNA_REFUSED_OPTIONS or last.startswith("_"):
        return "(nothing: this option names code, a nested object or an instruction to instantiate)"
    ok = value is None or isinstance(value, bool) or _is_number(value)
    ok = ok or (isinstance(value, str) and bool(_WORD.match(value)))
    return None if ok else "a number, true/false, null or a single word"


def _kind_joblib_backend(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if value in ("loky", "multiprocessing", "threading") else "loky, multiprocessing or threading"


def _kind_direction(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    items = value if isinstance(value, list) else [value]
    ok = bool(items) and all(v in ("minimize", "maximize") for v in items)
    return None if ok else "minimize, maximize or a list of them"


def _kind_storage(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    # start-up: the storage rule, only when a storage is named
    from nirspi_pipe.app.storage import check_storage

    sweep_dir = (hydra_node.get("sweep") or {}).get("dir")
    resolved = sweep_dir if isinstance(sweep_dir, str) and "${" not in sweep_dir else None
    why = check_storage(value, resolved)
    if why is None:
        return None
    return (
        f"null (SQLite in the sweep folder), sqlite:///<a file inside the sweep folder>, postgresql://… or "
        f"mysql://… ({why})"
    )


def _kind_optuna_target(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    prefix = allowlist.OPTUNA_TARGET_PREFIXES.get(key, "")
    sweeper = str((hydra_node.get("sweeper") or {}).get("_target_", ""))
    ok = (
        sweeper == allowlist.OPTUNA_SWEEPER
        and isinstance(value, str)
        and value.startswith(prefix)
        and value[len(prefix) :].isidentifier()
    )
    return None if ok else f"a class of {prefix.rstrip('.')} (with hydra/sweeper=optuna)"


def _kind_experiments(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    names = group_options("experiment")
    if _user_searchpath(hydra_node):  # a user's folder may hold them: each is composed and checked (_check_sweeps)
        ok = isinstance(value, list) and all(
            isinstance(v, str) and bool(_CONFIG_NAME.match(v)) and ".." not in v.split("/") for v in value
        )
        return None if value is None or ok else "a list of experiment names"
    ok = value is None or (isinstance(value, list) and all(isinstance(v, str) and v in names for v in value))
    return None if ok else f"a list of experiments among {', '.join(names)}"


def _kind_searchpath(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return _check_searchpath(value)


def _kind_sweep(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return None if isinstance(value, (str, int, float)) and not isinstance(value, bool) else "a sweep string"


_KIND_CHECKS: dict[str, Callable[[str, Any, dict[str, Any]], str | None]] = {
    "dir": _kind_dir,
    "subdir": _kind_subdir,
    "output_subdir": _kind_output_subdir,
    "name": _kind_name,
    "name_or_null": _kind_name_or_null,
    "mode": _kind_mode,
    "verbose": _kind_verbose,
    "bool": _kind_bool,
    "int": _kind_int,
    "n_jobs": _kind_n_jobs,
    "int_or_null": _kind_int_or_null,
    "number_or_null": _kind_number_or_null,
    "fraction": _kind_fraction,
    "scalar": _kind_scalar,
    "joblib_backend": _kind_joblib_backend,
    "direction": _kind_direction,
    "storage": _kind_storage,
    "optuna_target": _kind_optuna_target,
    "experiments": _kind_experiments,
    "searchpath": _kind_searchpath,
    "sweep": _kind_sweep,
}


def _check_kind(kind: str, key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    """None when ``value`` fits ``kind``, else the allowed values (for the message). Each kind
    has its checker in ``_KIND_CHECKS``."""
    check = _KIND_CHECKS.get(kind)
    if check is None:
        return "(nothing)"  # an unknown kind: fail closed
    return check(key, value, hydra_node)


def _user_searchpath(hydra_node: dict[str, Any]) -> bool:
    """Whether Hydra's search path holds an entry besides the default ones (a user's folder)."""
    defaults = set(default_searchpath())
    return any(str(entry) not in defaults for entry in hydra_node.get("searchpath") or [])


def _check_searchpath(value: Any) -> str | None:
    allowed = "the default entries and file:// folders that exist"
    if not isinstance(value, list):
        return allowed
    defaults = set(default_searchpath())
    for entry in value:
        if entry in defaults:
            continue
        if not isinstance(entry, str) or not entry.startswith("file://"):
            return allowed
        folder = Path(entry[len("file://") :])
        if not folder.is_dir() or any(ord(c) < 32 for c in entry):
            return allowed
    return None


def check_hydra_node(hydra_node: dict[str, Any], plain_keys: list[str] | None = None) -> list[tuple[str, str]]:
    """Hydra's node of a composed config (a plain, unresolved tree) against the allow-list;
    raises :class:`Refused`. Returns the sweeps it holds (``hydra.sweeper.params``) as
    ``(key, sweep string)`` pairs for the caller to check value by value.

    The reference is Hydra's node composed with nothing of the user's but the ``hydra/…``
    choices (cached per process and per choices). With ``plain_keys`` (the node was composed
    from the default config and search path with job group choices and plain value overrides
    only: :func:`_hydra_keys_if_plain`) it is not composed: what the user set in the node is
    those keys, which are checked."""
    user = _leaves(hydra_node)
    if plain_keys is not None:
        return _check_diffs(user, [(1, key) for key in sorted(set(plain_keys)) if key in user], hydra_node)
    changed = _changed_hydra_choices(hydra_node)
    ref = _leaves(_reference_node(changed))
    diffs: list[tuple[int, str]] = []
    for key in set(user) | set(ref):
        if any(_match(p, key) for p in allowlist.IGNORED_KEYS):
            continue
        if key in user and key in ref and user[key] == ref[key]:
            continue
        if key not in user and any(k.startswith(key + ".") for k in user):
            continue  # a node replaced by a subtree: its leaves are compared
        diffs.append((0 if key in user and key.endswith("_target_") else 1 if key in user else 2, key))
    return _check_diffs(user, diffs, hydra_node)


#: Leaves of a job's Hydra node that its launcher or sweeper sets for that job (job number and
#: id, the job's name (``hydra.main`` names it after the task's module, the compose API
#: ``app``), run mode, the keyed job folder): checked by kind, not compared with the checked node.
_JOB_TIME_KEYS = ("job.num", "job.id", "job.name", "mode", "sweep.subdir")

#: The leaves of Hydra's node that :func:`check_invocation` passed in this process (without the
#: keys Hydra fills and :data:`_JOB_TIME_KEYS`): :func:`check_job` takes a job's node equal to
#: one of them without composing the reference again.
_APPROVED: list[dict[str, Any]] = []


def _comparable_leaves(hydra_node: dict[str, Any]) -> dict[str, Any]:
    return {
        k: v
        for k, v in _leaves(hydra_node).items()
        if k not in _JOB_TIME_KEYS and not any(_match(p, k) for p in allowlist.IGNORED_KEYS)
    }


def check_job(hydra_cfg: Any, job_cfg: Any = None) -> None:
    """The second gate, in the job itself (issue 41): the Hydra node a job actually received
    (after its launcher's per-job composition, ``load_sweep_config``) against the allow-list,
    before the job's code runs; :class:`Refused` otherwise.

    * the overrides Hydra re-applies to the job (``hydra.overrides.hydra``) and the job's own
      (``hydra.overrides.task``) never set what Hydra fills nor place a group under ``hydra``;
    * every other leaf equals the node :func:`check_invocation` passed in this process, or,
      where there is none (a joblib or submitit worker) or it differs, the node is compared
      leaf by leaf with Hydra's default composition (:func:`check_hydra_node`); the job's
      number, id, mode and folder (``sweep.subdir``) are checked by kind, and the job folder
      after resolution is relative without ``..``;
    * ``job_cfg`` (the job's part): every ``_target_`` on the allow-list.

    ``hydra_cfg`` is the job's ``hydra`` node as OmegaConf (``HydraConfig.get()``), attached to
    its config so that ``${hydra.job.num}`` resolves."""
    raw = OmegaConf.to_container(hydra_cfg, resolve=False)
    if not isinstance(raw, dict):
        raise Refused("the job's Hydra node is not a mapping; allowed: the node Hydra composes")
    node: dict[str, Any] = {str(k): v for k, v in raw.items()}
    listed = node.get("overrides") or {}
    texts = [str(t) for k in ("hydra", "task") for t in (listed.get(k) or [])] if isinstance(listed, dict) else []
    _check_override_places([_parse_cached(t) for t in texts])
    leaves = _leaves(node)
    for key in _JOB_TIME_KEYS:
        kind = _kind_of(key)
        problem = _check_kind(kind, key, leaves.get(key), node) if kind and key in leaves else None
        if problem:
            raise Refused(f"hydra.{key}={_short(leaves.get(key))} is not allowed; allowed: {problem}")
    if _comparable_leaves(node) not in _APPROVED:
        full = {**node, "job": {**(node.get("job") or {}), "num": "???", "id": "???"}}
        check_hydra_node(full)
    _check_node_paths(hydra_cfg)
    if job_cfg is not None:
        job = job_cfg if isinstance(job_cfg, dict) else OmegaConf.to_container(job_cfg, resolve=False)
        try:
            check_targets({k: v for k, v in job.items() if k != "hydra"} if isinstance(job, dict) else job)
        except ConfigError as exc:
            raise Refused(str(exc)) from None


def refuse_job(cfg: Any) -> None:
    """:func:`check_job` on a job's whole composed config (a launcher's or sweeper's
    ``load_sweep_config``); a refusal is one line on stderr and ``SystemExit(2)``: the sweep
    stops before the job (and the others, composed alike) runs."""
    try:
        check_job(cfg.hydra, cfg)
    except Refused as exc:
        print(f"nirspi-run: error: job refused: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def _check_node_paths(hydra_cfg: Any) -> None:
    """A job's folders after resolution (``sweep.subdir``, ``output_subdir``, ``job.name``):
    relative, without ``..``."""
    for key in ("sweep.subdir", "output_subdir", "job.name"):
        try:
            value = OmegaConf.select(hydra_cfg, key, throw_on_missing=True)
        except Exception:  # noqa: BLE001 - a value only a later step fills: checked unresolved above
            continue
        if value is None:
            continue
        text = str(value)
        if text.startswith("/") or ".." in Path(text).parts or "\\" in text:
            raise Refused(f"hydra.{key}={text!r} is not allowed; allowed: a relative folder without '..'")


def _changed_hydra_choices(hydra_node: dict[str, Any]) -> list[tuple[str, str]]:
    """The ``hydra/…`` group choices that differ from the defaults, each checked: only the groups
    of :data:`allowlist.HYDRA_CHOICE_GROUPS` (and their subgroups that the defaults lack) may
    change, and not to a choice of :data:`allowlist.REFUSED_HYDRA_CHOICES`."""
    choices = {k: v for k, v in (hydra_node.get("runtime", {}).get("choices") or {}).items() if k.startswith("hydra/")}
    defaults = {k: v for k, v in _default_choices().items() if k.startswith("hydra/")}
    allowed_groups = allowlist.HYDRA_CHOICE_GROUPS
    changed: list[tuple[str, str]] = []
    for group in sorted(set(choices) | set(defaults)):
        if choices.get(group) == defaults.get(group):
            continue
        subgroup = group not in defaults and group.startswith(tuple(f"{g}/" for g in allowed_groups))
        if group not in allowed_groups and not subgroup:
            raise Refused(
                f"{group}={choices.get(group)} is not allowed: only the default may be used for {group}; "
                f"allowed changes: {', '.join(sorted(allowed_groups))}"
            )
        why = allowlist.REFUSED_HYDRA_CHOICES.get((group, str(choices.get(group))))
        if why:
            raise Refused(f"{group}={choices.get(group)} is not allowed: {why}")
        if group in choices:
            changed.append((group, choices[group]))
    return changed


def _reference_node(changed: list[tuple[str, str]]) -> Any:
    """Hydra's node composed with the ``hydra/…`` choices ``changed`` and nothing else of the
    user's; a choice that is no option (e.g. a file in a ``-cd`` folder) is refused by name."""
    try:
        return _baseline(tuple(changed))
    except Refused:
        group, option = changed[-1] if changed else ("hydra", None)
        names = _hydra_group_options(group)
        for g, o in changed:
            if o not in _hydra_group_options(g):
                group, option, names = g, o, _hydra_group_options(g)
                break
        raise Refused(
            f"{group}={option} is not an option; allowed: {', '.join(names) or '(none)'} "
            "(Hydra's, nirspi-pipe's and installed plugins' configs; a config folder cannot add one)"
        ) from None


def _check_diffs(
    user: dict[str, Any], diffs: list[tuple[int, str]], hydra_node: dict[str, Any]
) -> list[tuple[str, str]]:
    """The leaves of Hydra's node that differ from the reference (``(order, key)``) against the
    allow-list; :class:`Refused` for the first that is not allowed. Returns the sweeps."""
    sweeps: list[tuple[str, str]] = []
    for _, key in sorted(diffs):
        value = user.get(key)
        kind = _kind_of(key) if key in user else None
        shown = f"hydra.{key}"
        if kind is None:
            how = "removed" if key not in user else f"={_short(value)}"
            raise Refused(
                f"{shown}{how if how.startswith('=') else ' ' + how} is not allowed: Hydra's own settings may "
                f"change only at {_allowed_keys_text()}"
            )
        problem = _check_kind(kind, key, value, hydra_node)
        if problem:
            raise Refused(f"{shown}={_short(value)} is not allowed; allowed: {problem}")
        if kind == "sweep":
            sweeps.append((key[len("sweeper.params.") :], str(value)))
    return sweeps


def _allowed_keys_text() -> str:
    keys = ("run.dir", "sweep.dir", "sweep.subdir", "job.name", "verbose", "searchpath", "sweeper.params")
    return (
        ", ".join(f"hydra.{k}" for k in keys)
        + ", the launcher's and sweeper's documented options (nirspi_pipe.app.allowlist)"
    )


def _short(value: Any, limit: int = 80) -> str:
    return short_repr(value, limit)


# --------------------------------------------------------------------------- sweeps


def _candidates(ov: Any, group_opts: list[str] | None) -> list[Any]:
    """The values a sweep override can take: every one of a choice or range; the bounds of an
    interval (Optuna's ``interval(a,b)``); the matching options of a ``glob`` over a group."""
    value = ov.value()
    if isinstance(value, IntervalSweep):
        return [value.start, value.end]
    if isinstance(value, Glob):
        if group_opts is None:
            raise Refused(f"{ov.key_or_group}: glob() is allowed only over a config group")
        return list(value.filter(group_opts))
    try:
        return list(ov.sweep_iterator())
    except Exception as exc:  # noqa: BLE001 - what cannot be enumerated is refused
        raise Refused(f"{ov.key_or_group}={ov.input_line}: the sweep cannot be enumerated ({_one_line(exc)})") from None


def _parse(overrides: list[str]) -> list[Any]:
    parser = OverridesParser.create()
    out = []
    for text in overrides:
        try:
            out.append(parser.parse_override(text))
        except Exception as exc:  # noqa: BLE001 - a syntax error is refused here, not handed on
            first = str(exc).strip().splitlines()
            raise Refused(f"{text[:80]!r} is not a valid override: {_one_line(first[0] if first else exc)}") from None
    return out


@lru_cache(maxsize=4096)
def _parse_cached(text: str) -> Any:
    """:func:`_parse` of one override, cached: a sweep's jobs repeat the same overrides."""
    return _parse([text])[0]


def _is_hydra_key(key: str) -> bool:
    return key == "hydra" or key.startswith(("hydra.", "hydra/"))


# --------------------------------------------------------------------------- the check


def check_invocation(args: list[str], *, api: bool = False) -> Invocation:
    """Check what ``nirspi-run ARGS`` (or ``nirspi_pipe.run(ARGS)`` with ``api``) would do and
    return the :class:`Invocation` to hand to Hydra; :class:`Refused` (one line) otherwise.

    The steps, in order: the API takes overrides only; flags are matched exactly
    (:func:`parse_args`); ``-sc`` takes one shell word, other overrides have their nulls rewritten;
    ``-cd`` becomes a search-path entry; sweeps only with ``-m`` and never of Hydra's settings; the
    primary config must exist; then one composition, checked whole (:func:`_compose_checked`), and
    each sweep's values (:func:`_check_sweeps`)."""
    if api:
        _refuse_flags_in_api(args)
    flags, overrides = parse_args(list(args))
    overrides, compose_overrides = _job_overrides(flags, overrides)
    _check_searchpath_first(_parse(compose_overrides))  # before anything is composed or imported
    user_paths = bool(flags.get("--config-dir")) or any(
        ov.key_or_group == "hydra.searchpath" for ov in _parse(compose_overrides)
    )
    overrides, compose_overrides = _with_config_dir(flags, overrides, compose_overrides)
    parsed = _parse(compose_overrides)
    _check_override_places(parsed)
    _check_sweep_places(parsed, flags)
    config_name = _primary_config(flags)
    fixed = [o for o, ov in zip(compose_overrides, parsed, strict=True) if not ov.is_sweep_override()]
    name_options = not user_paths and "--shell-completion" not in flags  # one-line names for options and keys
    cfg = _compose_checked(config_name, fixed, compose_overrides, name_options)
    simple = None
    if config_name == CONFIG_NAME and not user_paths:
        simple = _hydra_keys_if_plain([ov for ov in parsed if not ov.is_sweep_override()])
    _check_composed(cfg, flags, simple)
    sweeps = [ov for ov in parsed if ov.is_sweep_override()]
    _check_sweeps(cfg, sweeps, fixed, config_name, user_paths, flags)
    _APPROVED.append(_comparable_leaves(OmegaConf.to_container(cfg.hydra, resolve=False)))  # type: ignore[arg-type]
    del _APPROVED[:-16]  # the latest few: a notebook calling nirspi_pipe.run in a loop keeps no more
    return Invocation(
        flags=flags,
        overrides=tuple(overrides),
        hydra_argv=(*_hydra_flags(flags), *overrides),
        config_name=config_name,
        config=cfg,
    )


def _refuse_flags_in_api(args: list[str]) -> None:
    """``nirspi_pipe.run(ARGS)`` takes overrides only: no flag."""
    for arg in args:
        if arg.startswith("-"):
            raise Refused(f"{arg[:60]} is not an override; allowed: key=value overrides (sweeps: nirspi-run -m)")


def _job_overrides(flags: dict[str, str | None], overrides: list[str]) -> tuple[list[str], list[str]]:
    """``(overrides for Hydra, overrides to compose)``: with ``-sc`` the one shell word is
    checked and nothing of it is composed; otherwise ``stage=null``/``off`` are rewritten
    (:func:`nirspi_pipe.app.validate.rewrite_nulls`) and both lists are the rewritten ones."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    if "--shell-completion" in flags:
        words = [o.partition("=") for o in overrides]
        if len(words) != 1 or words[0][0] not in ("install", "uninstall", "query") or words[0][2] not in _SHELLS:
            raise Refused(
                "-sc needs exactly one of install=SHELL, uninstall=SHELL, query=SHELL; allowed shells: "
                + ", ".join(_SHELLS)
            )
        if words[0][0] == "query" and "COMP_LINE" not in os.environ:  # Hydra would raise KeyError
            raise Refused(
                "-sc query=SHELL is what an installed completion calls, with COMP_LINE set by the shell; "
                "allowed here: -sc install=SHELL (then press TAB) or -sc uninstall=SHELL"
            )
        return overrides, []
    rewritten, problem = validate.rewrite_nulls(overrides)
    if problem:
        raise Refused(problem)
    return rewritten, rewritten


def _with_config_dir(
    flags: dict[str, str | None], overrides: list[str], compose_overrides: list[str]
) -> tuple[list[str], list[str]]:
    """``-cd DIR`` (taken out of ``flags``) as what Hydra does with it: DIR appended to the
    search path, one ``hydra.searchpath=[...]`` override in place of any given. Returns
    ``(overrides for Hydra, overrides to compose)``."""
    config_dir = flags.pop("--config-dir", None)
    if config_dir is None:
        return overrides, compose_overrides
    folder = Path(config_dir).resolve()
    if not folder.is_dir():
        raise Refused(f"--config-dir={config_dir!r} is not allowed; allowed: a folder that exists")
    parsed = _parse(compose_overrides)
    given = [ov for ov in parsed if ov.key_or_group == "hydra.searchpath"]
    base = given[-1].value() if given else default_searchpath()
    if not isinstance(base, list):
        raise Refused("hydra.searchpath is not allowed; allowed: a list of folders")
    entries = [*map(str, base), folder.as_uri()]
    compose_overrides = [o for o, ov in zip(compose_overrides, parsed, strict=True) if ov not in given]
    compose_overrides.append(f"hydra.searchpath=[{','.join(entries)}]")
    if "--shell-completion" not in flags:
        overrides = compose_overrides
    return overrides, compose_overrides


def _check_searchpath_first(parsed: list[Any]) -> None:
    """``hydra.searchpath`` overrides checked before the first composition (issue 41): Hydra
    imports a ``pkg://`` or ``structured://`` entry's module while it composes, so an entry that
    is not a default one or an existing ``file://`` folder is refused before that."""
    for ov in parsed:  # a package under hydra (+x@hydra.searchpath) is refused before compose too
        if ov.key_or_group != "hydra.searchpath":
            continue
        if ov.is_sweep_override() or ov.is_delete():
            raise Refused(f"{ov.input_line[:80]} is not allowed; allowed: hydra.searchpath=[file:///a/folder, ...]")
        problem = _check_searchpath(ov.value())
        if problem:
            raise Refused(f"hydra.searchpath={_short(ov.value())} is not allowed; allowed: {problem}")


def _check_override_places(parsed: list[Any]) -> None:
    """Overrides never set what Hydra fills itself (``hydra.overrides``, ``hydra.runtime``, the
    whole ``hydra`` node) and never place a group under ``hydra`` (``+scene@hydra.callbacks.x``):
    the package is Hydra's parsed one (``Override.package``), not a split of the text."""
    for ov in parsed:
        key = ov.key_or_group
        if key == "hydra" or key.startswith(("hydra.overrides", "hydra.runtime")):
            filled = ".".join(key.split(".")[:2])
            raise Refused(
                f"{ov.input_line[:80]} is not allowed: Hydra fills {filled} itself; allowed: set each Hydra "
                "key by its own override (hydra.run.dir=...)"
            )
        package = ov.package
        if package is not None and (package == "hydra" or package.startswith("hydra.") or package == "_global_.hydra"):
            raise Refused(
                f"{ov.get_key_element()[:80]}: a package under hydra is not allowed; allowed: the group's own "
                "package (leave out @...)"
            )


def _check_sweep_places(parsed: list[Any], flags: dict[str, str | None]) -> None:
    """A sweep only with ``-m``, and never of Hydra's own settings."""
    for ov in parsed:
        if ov.is_sweep_override() and _is_hydra_key(ov.key_or_group):
            raise Refused(f"{ov.input_line}: sweeping Hydra's own settings is not allowed")
        if ov.is_sweep_override() and "--multirun" not in flags:
            raise Refused(f"{ov.input_line} is a sweep; allowed: a sweep with -m only (nirspi-run -m ...)")


def _primary_config(flags: dict[str, str | None]) -> str:
    """The primary config's name (``-cn``): ours, or another config of nirspi-pipe's conf/."""
    config_name = flags.get("--config-name") or CONFIG_NAME
    if config_name != CONFIG_NAME and not _primary_exists(config_name):
        raise Refused(
            f"--config-name={config_name}: no such primary config; allowed: {CONFIG_NAME} or a config of "
            "nirspi-pipe's conf/ (files in a -cd folder are used as +experiment=NAME or group options)"
        )
    return config_name


def _compose_checked(config_name: str, fixed: list[str], compose_overrides: list[str], name_options: bool) -> Any:
    """The one composition (the sweeps' first values aside), with the job's keys and types
    checked on it; with ``name_options`` a refusal names the option or key rather than quoting
    Hydra's first line."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    try:
        cfg = _compose(config_name, fixed)
    except Refused:
        problem = validate.check_overrides(compose_overrides) if name_options else None
        if problem:  # the option or key by name, rather than Hydra's first line
            raise Refused(problem) from None
        raise
    if name_options:
        problem = validate.check_overrides(compose_overrides, composed=cfg)  # keys and types on this compose
        if problem:
            raise Refused(problem)
    return cfg


def _hydra_flags(flags: dict[str, str | None]) -> list[str]:
    """The flags handed on to Hydra, canonical (``--version`` and ``--plugins`` are ours)."""
    return [
        canonical if value is None else f"{canonical}={value}"
        for canonical, value in flags.items()
        if canonical not in ("--version", "--plugins")
    ]


def _plain(cfg: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """The job part (resolved where it resolves) and Hydra's node (unresolved)."""
    job_part = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
    try:
        job = OmegaConf.to_container(job_part, resolve=True)
    except (InterpolationKeyError, InterpolationResolutionError) as exc:
        names_hydra = "'hydra." in str(exc)  # ${hydra.job.name}: Hydra's node is masked out here
        if (isinstance(exc, InterpolationKeyError) and not names_hydra) or "Recursive interpolation" in str(exc):
            key = getattr(exc, "full_key", None) or "?"
            raise Refused(
                f"{key}: the interpolation does not resolve ({_one_line(str(exc).splitlines()[0])}); "
                "allowed: a value, or ${other.key} naming another key"
            ) from None
        job = OmegaConf.to_container(job_part, resolve=False)  # a resolver only a running app has
    except Exception:  # noqa: BLE001 - then checked unresolved
        job = OmegaConf.to_container(job_part, resolve=False)
    hydra_node = OmegaConf.to_container(cfg.hydra, resolve=False)
    return job, hydra_node  # type: ignore[return-value]


def _hydra_keys_if_plain(fixed: list[Any]) -> list[str] | None:
    """The ``hydra.…`` keys (below ``hydra.``) that ``fixed`` sets, when Hydra's node can differ
    from the default composition only at those keys or through trusted files; otherwise None.

    That holds when (the caller checks) the config is the default one and the search path is
    the default one (no ``-cd``, no ``hydra.searchpath``), and every override in ``fixed`` is
    either a choice of a job's config group (``scene=cube``, ``+experiment=paper_ci``: an option
    file of nirspi-pipe or an installed plugin, which is trusted and may set Hydra's settings) or
    a plain value override of an existing key (no ``+``/``~``/``@``), each ``hydra.…`` one
    setting one allow-listed leaf to a scalar. Hydra composes the defaults tree first (only the
    config name, the search path and group choices shape it) and then sets value overrides, so
    those keys are all that comes from the user, and the reference composition is not needed.
    A ``hydra/…`` choice, a package (``@``) or a deletion needs the reference: None."""
    from nirspi_pipe.app.validate import _group_exists  # start-up: loads 15 modules of ours (27 ms here)

    keys: list[str] = []
    for ov in fixed:
        key = ov.key_or_group
        if ov.is_delete() or ov.package is not None or key == "hydra" or key.startswith("hydra/"):
            return None
        if _group_exists(key):
            continue  # a trusted option file (its name is checked to exist: validate.check_overrides)
        if ov.is_add() or ov.is_force_add() or _group_exists(key.split("/", 1)[0]):
            return None
        if key.startswith("hydra."):
            leaf = key[len("hydra.") :]
            kind = _kind_of(leaf)
            if kind is None or kind == "searchpath" or isinstance(ov.value(), (dict, list)):
                return None
            keys.append(leaf)
    return keys


def _check_composed(
    cfg: Any, flags: dict[str, str | None], plain_keys: list[str] | None = None
) -> list[tuple[str, str]]:
    """One composed configuration: Hydra's node against the allow-list, every target, the job's
    keys and stage nodes, and (``-m``) the sweep settings. Returns the sweeper's params.
    ``plain_keys``: see :func:`_hydra_keys_if_plain` (then only those keys of Hydra's node are
    compared)."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    job, hydra_node = _plain(cfg)
    params = check_hydra_node(hydra_node, plain_keys)
    try:
        check_targets(job)
        check_targets(hydra_node, "hydra")
    except ConfigError as exc:
        raise Refused(str(exc)) from None
    problem = validate.check_plain_keys(job) or validate._check_stage_nodes(job)
    if not problem and "--multirun" in flags:
        resolved = _resolved_hydra(cfg)
        problem = validate._check_sweep_settings(resolved)
    if problem:
        raise Refused(problem)
    _check_output_paths(cfg)
    return params


def _resolved_hydra(cfg: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ("launcher", "sweeper"):
        try:
            out[key] = OmegaConf.to_container(cfg.hydra[key], resolve=True)
        except Exception:  # noqa: BLE001 - values only a running app has
            out[key] = OmegaConf.to_container(cfg.hydra[key], resolve=False)
    return out


def _check_output_paths(cfg: Any) -> None:
    """The job folders after resolution: ``hydra.sweep.subdir`` and ``hydra.output_subdir``
    relative and without ``..``, so nothing is written above the run or sweep folder (the check
    a job's own node gets, :func:`_check_node_paths`)."""
    _check_node_paths(cfg.hydra)


def _check_sweeps(
    cfg: Any,
    sweeps: list[Any],
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> None:
    """Every value of every sweep (command line and ``hydra.sweeper.params``) for its key."""
    job, hydra_node = _plain(cfg)
    sweep_texts = [ov.input_line for ov in sweeps]
    sweep_texts += [f"{k}={v}" for k, v in ((hydra_node.get("sweeper") or {}).get("params") or {}).items()]
    experiments = (hydra_node.get("sweeper") or {}).get("experiments") or []
    if experiments and user_paths:
        sweep_texts += _experiment_sweeps(experiments, fixed, config_name, flags)
    groups = all_groups()
    grid: list[list[str]] = []  # each swept group's key elements and values, as the jobs will set them
    n_own = len(sweeps) + len((hydra_node.get("sweeper") or {}).get("params") or {})
    for i, ov in enumerate(_parse(sweep_texts)):
        key = ov.key_or_group  # Hydra's parse: no package, no +/~ prefix
        if _is_hydra_key(key):
            raise Refused(f"{ov.input_line}: sweeping Hydra's own settings is not allowed")
        if ov.is_delete():
            continue
        is_group = key in groups
        values = _candidates(ov, group_options(key) if is_group else None) if ov.is_sweep_override() else [ov.value()]
        for value in values:
            if is_group:
                _check_group_value(ov, key, value, fixed, config_name, user_paths, flags)
            else:
                _check_key_value(job, key, value)
        if is_group and i < n_own:
            grid.append([f"{ov.get_key_element()}={'null' if v is None else v}" for v in values])
    if user_paths and len(grid) > 1:
        _check_group_combinations(grid, fixed, config_name, hydra_node, flags)


#: At most this many combinations of swept config groups are composed before a sweep with a user's
#: config folder and Hydra's own sweeper and launcher (assumed: 256 compositions take about 25 s
#: at ~0.1 s each, ``nirspi-bench compose``; beyond that the nirspi launcher checks job by job).
MAX_CHECKED_COMBINATIONS = 256

#: Sweepers and launchers that compose each job and pass its Hydra node through :func:`check_job`
#: before anything of the job runs (the nirspi sweeper's :meth:`compose`, the nirspi launcher's
#: ``launch``); with Hydra's own (basic, joblib, submitit, Optuna's) the job gate in the task
#: function comes after Hydra configured the job's logging and wrote ``.hydra/``.
GATED_BEFORE_LAUNCH = frozenset(
    {
        "hydra_plugins.nirspi_pipe_sweeper.NirspiSweeper",
        "hydra_plugins.nirspi_pipe_sweeper.NirspiOptunaSweeper",
        "hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher",
    }
)


def _check_group_combinations(
    grid: list[list[str]], fixed: list[str], config_name: str, hydra_node: dict[str, Any], flags: dict[str, str | None]
) -> None:
    """With a user's config folder, two swept groups can make together what neither makes alone:
    an option file's defaults list may pick an option by interpolation (``override
    /hydra/job_logging: ${metrics}``), so ``+experiment=a metrics=x`` chooses a logging config
    that ``+experiment=a`` and ``metrics=x`` each leave alone. Every combination is composed as
    the launcher will compose the job (``load_sweep_config``: Hydra's overrides, then the job's)
    and checked whole, unless the sweeper or the launcher is one of :data:`GATED_BEFORE_LAUNCH`,
    which composes and checks each job before it runs (the same compositions, done once). With
    Hydra's own pair, beyond :data:`MAX_CHECKED_COMBINATIONS` the sweep is refused."""
    targets = {str((hydra_node.get(k) or {}).get("_target_")) for k in ("sweeper", "launcher")}
    if targets & GATED_BEFORE_LAUNCH:
        return
    count = math.prod(len(values) for values in grid)
    if count > MAX_CHECKED_COMBINATIONS:
        raise Refused(
            f"a sweep of {count} combinations of config groups with a config folder of yours is checked "
            f"combination by combination before Hydra's launchers run it, at most {MAX_CHECKED_COMBINATIONS}; "
            "allowed: fewer combinations, or the nirspi sweeper or launcher (the defaults), which check each job "
            "before it starts"
        )
    for combination in itertools.product(*grid):
        _check_composed(_compose(config_name, [*fixed, *combination]), flags)


def _experiment_sweeps(
    experiments: list[str], fixed: list[str], config_name: str, flags: dict[str, str | None]
) -> list[str]:
    """Each experiment of a meta-experiment composed (and checked) as the sweeper will compose
    it; returns the sweeps each one holds, as ``key=sweep`` texts."""
    shared = [o for o in fixed if not o.lstrip("+~").startswith("experiment=")]  # as NirspiSweeper does
    texts: list[str] = []
    for name in experiments:
        one = _compose(config_name, [f"+experiment={name}", *shared])
        _check_composed(one, flags)
        texts += [f"{k}={v}" for k, v in ((_plain(one)[1].get("sweeper") or {}).get("params") or {}).items()]
    return texts


def _check_group_value(
    ov: Any,
    key: str,
    value: Any,
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> None:
    """One option of a swept config group: a shipped or plugin option (or null/off); with a
    user's config folder the option may come from there, so the job it makes is composed and
    checked whole."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    text = "null" if value is None else str(value)
    allowed = group_options(key)
    if text not in ("null", "None", validate.OFF_OPTION) and text not in allowed and not user_paths:
        raise Refused(f"{key}={text} is not an option; allowed: {', '.join(allowed)} (or null)")
    if user_paths:  # composed as Hydra composes it: the parsed key element (+, ++, @package) kept
        _check_composed(_compose(config_name, [*fixed, f"{ov.get_key_element()}={text}"]), flags)


def _check_key_value(job: dict[str, Any], key: str, value: Any) -> None:
    """One value of a swept key: its targets allowed, and the job with it set passing the key
    and type checks."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    try:
        if key == "_target_" or key.endswith("._target_"):
            check_target(value, key)
        else:
            check_targets(value, key)
    except ConfigError as exc:
        raise Refused(str(exc)) from None
    one = OmegaConf.create(job)
    try:
        OmegaConf.update(one, key, value, merge=False, force_add=True)
    except Exception as exc:  # noqa: BLE001 - a value that cannot be set is refused
        raise Refused(f"{key}={_short(value)} cannot be set: {_one_line(exc)}") from None
    problem = validate.check_plain_keys(OmegaConf.to_container(one, resolve=False))
    if problem:
        raise Refused(problem)
