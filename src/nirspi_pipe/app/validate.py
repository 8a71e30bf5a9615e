"""Check command-line overrides before Hydra composes them, so that an unknown option gives one
line naming the group and its allowed values instead of Hydra's multi-line report."""

from __future__ import annotations

import difflib
import inspect
import pkgutil
import re
from typing import Any

from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf

from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME, all_groups, config_groups, group_options
from nirspi_pipe.app.launchsettings import DEFAULT_TIMEOUT_S, check_launcher_settings
from nirspi_pipe.app.objective import ObjectiveError, objective_names
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.instantiate import Plan, accepted_keys, user_key
from nirspi_pipe.pipeline import MODEL_OF_NOTHING, STAGE_GROUPS, check_types
from nirspi_pipe.targets import find_targets, locate

__all__ = [
    "check_plain_keys",
    "check_stage_nodes",
    "check_sweep_settings",
    "group_exists",
    "check_overrides",
    "rewrite_nulls",
    "hydra_floats",
    "group_options",
    "config_groups",
    "REQUIRED_GROUPS",
    "OFF_OPTION",
]

#: Stage groups a run cannot do without: ``solver=null`` is refused with one line.
REQUIRED_GROUPS = ("source", "scan", "solver")
#: The option of every optional group that switches it off (``conf/<group>/off.yaml``); Hydra
#: does not accept ``group=null`` for a config group, so ``nirspi-run`` rewrites null to it.
OFF_OPTION = "off"
_NULLS = ("null", "None")

#: Hydra flags followed by a value.
_FLAGS_WITH_VALUE = {
    "-cn",
    "--config-name",
    "-cp",
    "--config-path",
    "-cd",
    "--config-dir",
    "-c",
    "--cfg",
    "-p",
    "--package",
    "--experimental-rerun",
    "-sc",
    "--shell-completion",
}


def group_exists(group: str) -> bool:
    return group in all_groups()


def _group_of(arg: str) -> str | None:
    """The config group an override ``[+~]group[@pkg]=value`` sets, or None."""
    if "=" not in arg or arg.startswith("-"):
        return None
    key = arg.split("=", 1)[0].lstrip("+~").split("@", 1)[0]
    return key if key and not key.startswith("hydra") and group_exists(key) else None


#: YAML's spellings of the non-finite floats (what config files, records and error messages use:
#: ``fog.extent_mm=.inf``) → Hydra's override grammar, which reads only ``inf``/``-inf``/``nan``.
YAML_FLOATS = {".inf": "inf", "+.inf": "inf", "-.inf": "-inf", ".nan": "nan"}
_VALUE_TOKENS = re.compile(r"([,\[\]\s])")


def hydra_floats(arg: str) -> str:
    """``key=.inf`` (also ``-.inf``, ``.nan``, any case, in a sweep or a list: ``key=350,.inf``)
    as Hydra reads it: ``key=inf``; quoted values, sweep functions and anything else unchanged."""
    if "=" not in arg or arg.startswith("-"):
        return arg
    head, value = arg.split("=", 1)
    if any(c in value for c in "()'\"{}") or "." not in value:
        return arg
    tokens = _VALUE_TOKENS.split(value)
    return head + "=" + "".join(YAML_FLOATS.get(t.lower(), t) for t in tokens)


def rewrite_nulls(args: list[str]) -> tuple[list[str], str | None]:
    """``group=null`` (also in a sweep list, ``upscale=null,bicubic``) becomes the group's
    ``off`` option, which sets the stage to null; ``solver=null`` (a required group) is a
    one-line problem. YAML's ``.inf``/``-.inf``/``.nan`` (the spelling config files and the
    error messages use) become Hydra's ``inf``/``-inf``/``nan`` (:func:`hydra_floats`). Returns
    the new arguments and the problem, if any."""
    out: list[str] = []
    skip = False
    for arg in args:
        if skip or arg.startswith("-"):
            skip = (not skip) and arg in _FLAGS_WITH_VALUE
            out.append(arg)
            continue
        arg = hydra_floats(arg)
        group = _group_of(arg)
        if group is None:
            out.append(arg)
            continue
        head, value = arg.split("=", 1)
        tokens = [t.strip() for t in value.split(",")]
        if group in MODEL_OF_NOTHING and any(t in (*_NULLS, OFF_OPTION) for t in tokens):
            # refused before any job runs (the runner refuses it too: pipeline.run_pipeline)
            return args, (
                f"{group}={value} is not allowed; allowed: {MODEL_OF_NOTHING[group]}; "
                f"{group} is a model of the simulated camera, not a stage"
            )
        if not any(t in _NULLS for t in tokens) or any(c in value for c in "()[]{}'\""):
            out.append(arg)  # no null, or a sweep function/quoted value: left to Hydra
            continue
        if group in REQUIRED_GROUPS:
            return args, (
                f"{group}=null is not allowed: a run needs a {group} stage; allowed: {', '.join(group_options(group))}"
            )
        if OFF_OPTION not in group_options(group):
            out.append(arg)
            continue
        out.append(head + "=" + ",".join(OFF_OPTION if t in _NULLS else t for t in tokens))
    return out, None


def _override_args(args: list[str]) -> list[str]:
    out, skip = [], False
    for a in args:
        if skip:
            skip = False
            continue
        if a.startswith("-"):
            skip = a in _FLAGS_WITH_VALUE
            continue
        out.append(a)
    return out


def check_overrides(args: list[str], composed: Any = None) -> str | None:
    """Return a one-line problem with the group choices in ``args``, or None when they are fine
    (or when they are not ours to judge: syntax errors and Hydra's own groups go to Hydra).

    ``composed``: the configuration of every non-sweep override in ``args``, already composed
    (:func:`nirspi_pipe.app.entry.check_invocation` composes it anyway); the keys and types are
    then checked on it instead of composing again, unless a config group is swept (its first
    option would be composed here)."""
    overrides = _override_args(args)
    extra_dirs = any(a.partition("=")[0] in ("-cd", "--config-dir") for a in args)
    if not overrides or extra_dirs or any(o.startswith("hydra.searchpath") for o in overrides):
        return None  # no overrides, or a search path we do not see: Hydra judges
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException:
        return None
    choices: list[str] = []
    for ov in parsed:
        group = ov.key_or_group.split("@", 1)[0]
        if ov.is_delete() or group.startswith("hydra") or not group_exists(group):
            continue
        try:
            values = list(ov.sweep_string_iterator()) if ov.is_sweep_override() else [ov.get_value_element_as_str()]
        except HydraException:  # interval(), glob(): checked by their candidates in nirspi_pipe.app.entry
            continue
        allowed = group_options(group)
        for value in values:
            if value in ("null", "None") or value in allowed:
                continue
            return f"{group}={value} is not an option; allowed: {', '.join(allowed)} (or null)"
        choices.append(f"{'+' if ov.is_add() else ''}{ov.key_or_group}={values[0]}")
        if ov.is_sweep_override():
            composed = None  # the sweep's first option is composed below, as a job will be
    return _check_keys(parsed, choices, composed)


def _compose_or_none(overrides: list[str], config_name: str | None = None, hydra: bool = False) -> Any:
    """The composed config (with Hydra's node when ``hydra``), or None when Hydra cannot compose
    it (it reports that itself)."""
    try:
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            return compose(config_name or CONFIG_NAME, overrides=overrides, return_hydra_config=hydra)
    except Exception:  # noqa: BLE001 - Hydra reports composition problems itself
        return None


def _check_keys(parsed: list[Any], choices: list[str], composed: Any = None) -> str | None:
    """Unknown keys (``scene.fooo=1`` without ``+``): name the key and list the valid ones; then
    values of the wrong type (``scene.distance_mm=abc``, also in a sweep list), in the words of a
    wrong value.

    One composition with the group choices and the single values when it succeeds (then no
    single-value key is unknown, and value overrides add no keys, so the keys are those of the
    choices alone); only when it fails, a second with the choices alone to name the key. With
    ``composed`` (all single-value overrides applied), that one is used instead of the first."""
    values = [
        ov
        for ov in parsed
        if not ov.is_add()
        and not ov.is_delete()
        and not ov.is_force_add()
        and not ov.key_or_group.startswith("hydra")
        and not group_exists(ov.key_or_group)
    ]
    keys = [ov.key_or_group for ov in values]
    if not keys:
        return None
    if composed is not None:
        job = OmegaConf.masked_copy(composed, [str(k) for k in composed if k != "hydra"])
        return _unknown_key(job, keys) or _check_types(job, values)
    fixed = [f"{ov.key_or_group}={ov.get_value_element_as_str()}" for ov in values if not ov.is_sweep_override()]
    cfg = _compose_or_none([*choices, *fixed])
    if cfg is None:
        base = _compose_or_none(choices)
        return None if base is None else _unknown_key(base, keys)
    return _unknown_key(cfg, keys) or _check_types(cfg, values)


def _unknown_key(cfg: Any, keys: list[str]) -> str | None:
    """The first of ``keys`` that ``cfg`` does not have, as one line naming the allowed ones."""
    for key in keys:
        top = key.split(".", 1)[0]
        if top not in cfg.keys():  # keys() keeps ??? values
            known_top = sorted({str(k) for k in cfg.keys()} | {g.split("/")[0] for g in all_groups()})
            near = difflib.get_close_matches(top, known_top, n=1)
            hint = f"did you mean {near[0]}{key[len(top) :]}? " if near else ""
            return f"{key}: {top} is not a key or group; {hint}allowed: {', '.join(known_top)}"
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if isinstance(node, DictConfig) and leaf not in node.keys():  # keys() keeps ??? values
            where = parent or "the top level"
            known = ", ".join(sorted(str(k) for k in node if str(k) != "_target_"))
            return f"{key} is not a key of {where}; allowed keys: {known} (or +{key}=... to add one)"
    return None


def _check_types(cfg: Any, values: list[Any]) -> str | None:
    """The stage nodes of ``cfg`` (composed with the group choices and the single values) checked
    against their targets' annotations (:func:`nirspi_pipe.pipeline.check_types`); each value of
    a sweep list is put in turn into it. The first wrong type as one line."""
    runs: list[tuple[Any, tuple[str, ...]]] = [(cfg, ("camera", *STAGE_GROUPS))]

    for ov in values:
        if not ov.is_sweep_override():
            continue
        try:
            swept = list(ov.sweep_iterator())
        except HydraException:  # interval(), glob(): their candidates are checked in nirspi_pipe.app.entry
            continue
        for value in swept:
            one = cfg.copy()
            try:
                OmegaConf.update(one, ov.key_or_group, value, merge=False)
            except Exception:  # noqa: BLE001 - Hydra reports it when it composes the job
                continue
            runs.append((one, (ov.key_or_group.split(".", 1)[0],)))
    for config, groups in runs:
        nodes = {group: config.get(group) for group in groups if config.get(group) is not None}
        plan = Plan.of(nodes)  # one conversion of the stage nodes; their targets checked once (check_once)
        for group in nodes:
            try:
                check_types(plan.config[group], group, plan)
            except ConfigError as exc:
                return str(exc)
    return None


#: Top-level keys of a job's config that are not config groups (conf/config.yaml).
PLAIN_KEYS = ("camera", "seed", "tables", "output", "objective")
#: ``output``'s keys, each true or false (conf/config.yaml).
OUTPUT_KEYS = ("arrays", "images", "quiet")


def _table_names() -> tuple[str, ...]:
    """The paper tables a config may list under ``tables`` (modules of nirspi_pipe.tables)."""
    import nirspi_pipe.tables  # start-up: loads pandas, pyarrow, cloudpickle (208 ms here)

    return tuple(
        sorted(m.name for m in pkgutil.iter_modules(nirspi_pipe.tables.__path__) if not m.name.startswith("_"))
    )


def check_plain_keys(config: Any, groups: frozenset[str] | None = None) -> str | None:
    """Top-level keys, ``output`` and ``tables`` of a composed job config (a plain dict, without
    the ``hydra`` node): a key that is neither a config group nor one of :data:`PLAIN_KEYS`, an
    unknown ``output`` key, a non-boolean ``output`` value or an unknown table, as one line.
    (Stage nodes are checked against their classes when built: :func:`nirspi_pipe.pipeline.build`.)"""
    tops = {g.split("/")[0] for g in (all_groups() if groups is None else groups)} | set(PLAIN_KEYS)
    for key in config:
        if str(key) not in tops and str(key) != "hydra":
            near = difflib.get_close_matches(str(key), sorted(tops), n=1)
            hint = f"did you mean {near[0]}? " if near else ""
            return f"{key}: {key} is not a key or group; {hint}allowed: {', '.join(sorted(tops))}"
    output = config.get("output")
    if output is not None and not isinstance(output, dict):
        return f"output={output!r} is not allowed; allowed: a node with keys {', '.join(OUTPUT_KEYS)}"
    for key, value in (output or {}).items():
        if key not in OUTPUT_KEYS:
            return f"output.{key} is not a key of output; allowed keys: {', '.join(OUTPUT_KEYS)}"
        if not isinstance(value, bool):
            return f"output.{key}={value!r} is not allowed; allowed: true or false"

    try:
        objective_names(config.get("objective"))
    except ObjectiveError as exc:
        return str(exc)
    tables = config.get("tables")
    names = _table_names()
    if tables is not None and not isinstance(tables, list):
        return f"tables={tables!r} is not allowed; allowed: a list of {', '.join(names)}"
    for name in tables or []:
        if name not in names:
            return f"tables: {name!r} is not a table; allowed: {', '.join(names)}"
    return None


def check_sweep_settings(hydra_node: dict[str, Any]) -> str | None:
    """The nirspi launcher's ``n_jobs``/``timeout_s`` (:mod:`nirspi_pipe.app.launchsettings`, the
    launcher's own check) and the sweeper's ``allow_failures``, as one line (Hydra would wrap
    them in its multi-line report)."""
    launcher = hydra_node.get("launcher") or {}
    if str(launcher.get("_target_", "")).endswith(".NirspiLauncher"):
        try:
            check_launcher_settings(launcher.get("n_jobs", -1), launcher.get("timeout_s", DEFAULT_TIMEOUT_S))
        except ConfigError as exc:
            return str(exc)
    sweeper = hydra_node.get("sweeper") or {}
    allow = sweeper.get("allow_failures", False)
    if str(sweeper.get("_target_", "")).endswith(".NirspiSweeper") and not isinstance(allow, bool):
        return f"hydra.sweeper.allow_failures={allow!r} is not allowed; allowed: true or false"
    return None


def check_stage_nodes(job: dict[str, Any], plan: Plan | None = None) -> str | None:
    """Every node with a ``_target_`` in the stage groups (allowed: checked above) has only keys
    its class takes, with the annotated types: ``+scene.bogus=1`` stops before any job, not in
    every job. A class taking ``**kwargs`` accepts any key. ``plan``: the checked plan of ``job``
    (its classes are imported once and its targets not checked again)."""
    for group in ("camera", *STAGE_GROUPS):
        node = job.get(group)
        if not isinstance(node, dict):
            continue
        for key, target in find_targets(node, group):
            path = key[: -len("._target_")]
            sub: Any = node
            for part in path.split(".")[1:]:
                sub = sub[int(part)] if isinstance(sub, list) else sub[part]
            try:
                cls = plan.resolve(target, key) if plan is not None else locate(str(target))
                params = inspect.signature(cls).parameters
            except (TypeError, ValueError):
                continue
            if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
                continue
            for name in sub:
                if not str(name).startswith("_") and name not in params:
                    where, _ = user_key(f"{path}.{name}", group)  # source.effects.fog.x is fog.x to the user
                    return f"{where} is not a key; allowed keys: {accepted_keys(sub) or '(none)'}"
        try:
            check_types(node, group, plan)
        except ConfigError as exc:
            return str(exc)
    return None
