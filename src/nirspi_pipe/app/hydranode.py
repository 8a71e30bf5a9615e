"""Hydra's node against the allow-list (issue 32, 41): the node of a composed configuration is
compared with the one composed without the user's overrides, config folder or config name (only
the ``hydra/…`` choices kept); a difference outside the allow-list of
:mod:`nirspi_pipe.app.allowlist` is refused, each allowed key checked by its kind
(:func:`check_kind`). :func:`check_job` is the second gate, in the job itself: the node a job
actually received, before the job's code runs.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from nirspi_pipe.app import allowlist
from nirspi_pipe.app.composition import (
    baseline,
    default_choices,
    default_searchpath,
    hydra_group_options,
    parse_override_cached,
    short_value,
)
from nirspi_pipe.app.configs import group_options
from nirspi_pipe.app.flags import CONFIG_NAME_PATTERN, PACKAGE_PATTERN, Refused
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.targets import check_targets

__all__ = [
    "APPROVED",
    "check_hydra_node",
    "check_job",
    "check_kind",
    "check_node_paths",
    "check_override_places",
    "check_searchpath",
    "comparable_leaves",
    "flat_leaves",
    "key_matches",
    "kind_of",
    "refuse_job",
]

_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}$")
_WORD = re.compile(r"^[A-Za-z0-9_.:+-]{1,100}$")
_SUBDIR_PART = re.compile(r"^[A-Za-z0-9_.=,+-]+$")
_SUBDIR_INTERPOLATIONS = ("${hydra.job.num}", "${hydra.job.id}", "${hydra.job.name}")


def flat_leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted key → value for every leaf of a plain tree (lists and empty dicts are leaves)."""
    if isinstance(node, dict) and node:
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(flat_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: node}


def key_matches(pattern: str, key: str) -> bool:
    pp, kk = pattern.split("."), key.split(".")
    if pp[-1] == "**":
        return len(kk) >= len(pp) and all(p in ("*", k) for p, k in zip(pp[:-1], kk, strict=False))
    return len(pp) == len(kk) and all(p in ("*", k) for p, k in zip(pp, kk, strict=True))


def kind_of(key: str) -> str | None:
    for pattern, kind in allowlist.HYDRA_KEYS.items():
        if key_matches(pattern, key):
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
    ok = isinstance(value, bool) or all(isinstance(v, str) and PACKAGE_PATTERN.match(v) for v in items)
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
            isinstance(v, str) and bool(CONFIG_NAME_PATTERN.match(v)) and ".." not in v.split("/") for v in value
        )
        return None if value is None or ok else "a list of experiment names"
    ok = value is None or (isinstance(value, list) and all(isinstance(v, str) and v in names for v in value))
    return None if ok else f"a list of experiments among {', '.join(names)}"


def _kind_searchpath(key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
    return check_searchpath(value)


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


def check_kind(kind: str, key: str, value: Any, hydra_node: dict[str, Any]) -> str | None:
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


def check_searchpath(value: Any) -> str | None:
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
    user = flat_leaves(hydra_node)
    if plain_keys is not None:
        return _check_diffs(user, [(1, key) for key in sorted(set(plain_keys)) if key in user], hydra_node)
    changed = _changed_hydra_choices(hydra_node)
    ref = flat_leaves(_reference_node(changed))
    diffs: list[tuple[int, str]] = []
    for key in set(user) | set(ref):
        if any(key_matches(p, key) for p in allowlist.IGNORED_KEYS):
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
APPROVED: list[dict[str, Any]] = []


def comparable_leaves(hydra_node: dict[str, Any]) -> dict[str, Any]:
    return {
        k: v
        for k, v in flat_leaves(hydra_node).items()
        if k not in _JOB_TIME_KEYS and not any(key_matches(p, k) for p in allowlist.IGNORED_KEYS)
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
    node = _job_node(hydra_cfg)
    _check_job_time_keys(node)
    if comparable_leaves(node) not in APPROVED:
        full = {**node, "job": {**(node.get("job") or {}), "num": "???", "id": "???"}}
        check_hydra_node(full)
    check_node_paths(hydra_cfg)
    if job_cfg is not None:
        _check_job_targets(job_cfg)


def _job_node(hydra_cfg: Any) -> dict[str, Any]:
    """The job's Hydra node as plain data, once the overrides re-applied to the job
    (``hydra.overrides.hydra`` and ``.task``) set nothing Hydra fills nor place a group under it."""
    raw = OmegaConf.to_container(hydra_cfg, resolve=False)
    if not isinstance(raw, dict):
        raise Refused("the job's Hydra node is not a mapping; allowed: the node Hydra composes")
    node: dict[str, Any] = {str(k): v for k, v in raw.items()}
    listed = node.get("overrides") or {}
    texts = [str(t) for k in ("hydra", "task") for t in (listed.get(k) or [])] if isinstance(listed, dict) else []
    check_override_places([parse_override_cached(t) for t in texts])
    return node


def _check_job_time_keys(node: dict[str, Any]) -> None:
    """The job's number, id, mode and folder, checked by kind."""
    leaves = flat_leaves(node)
    for key in _JOB_TIME_KEYS:
        kind = kind_of(key)
        problem = check_kind(kind, key, leaves.get(key), node) if kind and key in leaves else None
        if problem:
            raise Refused(f"hydra.{key}={short_value(leaves.get(key))} is not allowed; allowed: {problem}")


def _check_job_targets(job_cfg: Any) -> None:
    """Every ``_target_`` of the job's part of its config (all but ``hydra``) on the allow-list."""
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


def check_node_paths(hydra_cfg: Any) -> None:
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
    defaults = {k: v for k, v in default_choices().items() if k.startswith("hydra/")}
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
        return baseline(tuple(changed))
    except Refused:
        group, option = changed[-1] if changed else ("hydra", None)
        names = hydra_group_options(group)
        for g, o in changed:
            if o not in hydra_group_options(g):
                group, option, names = g, o, hydra_group_options(g)
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
        kind = kind_of(key) if key in user else None
        shown = f"hydra.{key}"
        if kind is None:
            how = "removed" if key not in user else f"={short_value(value)}"
            raise Refused(
                f"{shown}{how if how.startswith('=') else ' ' + how} is not allowed: Hydra's own settings may "
                f"change only at {_allowed_keys_text()}"
            )
        problem = check_kind(kind, key, value, hydra_node)
        if problem:
            raise Refused(f"{shown}={short_value(value)} is not allowed; allowed: {problem}")
        if kind == "sweep":
            sweeps.append((key[len("sweeper.params.") :], str(value)))
    return sweeps


def _allowed_keys_text() -> str:
    keys = ("run.dir", "sweep.dir", "sweep.subdir", "job.name", "verbose", "searchpath", "sweeper.params")
    return (
        ", ".join(f"hydra.{k}" for k in keys)
        + ", the launcher's and sweeper's documented options (nirspi_pipe.app.allowlist)"
    )


def check_override_places(parsed: list[Any]) -> None:
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
