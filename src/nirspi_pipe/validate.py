"""Check command-line overrides before Hydra composes them, so that an unknown option gives one
line naming the group and its allowed values instead of Hydra's multi-line report."""

from __future__ import annotations

from typing import Any

from nirspi_pipe.configs import CONFIG_MODULE, CONFIG_NAME, all_groups, config_groups, group_options

__all__ = ["check_overrides", "rewrite_nulls", "group_options", "config_groups", "REQUIRED_GROUPS", "OFF_OPTION"]

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


def _group_exists(group: str) -> bool:
    return group in all_groups()


def _group_of(arg: str) -> str | None:
    """The config group an override ``[+~]group[@pkg]=value`` sets, or None."""
    if "=" not in arg or arg.startswith("-"):
        return None
    key = arg.split("=", 1)[0].lstrip("+~").split("@", 1)[0]
    return key if key and not key.startswith("hydra") and _group_exists(key) else None


def rewrite_nulls(args: list[str]) -> tuple[list[str], str | None]:
    """``group=null`` (also in a sweep list, ``upscale=null,bicubic``) becomes the group's
    ``off`` option, which sets the stage to null; ``solver=null`` (a required group) is a
    one-line problem. Returns the new arguments and the problem, if any."""
    out: list[str] = []
    skip = False
    for arg in args:
        if skip or arg.startswith("-"):
            skip = (not skip) and arg in _FLAGS_WITH_VALUE
            out.append(arg)
            continue
        group = _group_of(arg)
        if group is None:
            out.append(arg)
            continue
        head, value = arg.split("=", 1)
        tokens = [t.strip() for t in value.split(",")]
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


def check_overrides(args: list[str]) -> str | None:
    """Return a one-line problem with the group choices in ``args``, or None when they are fine
    (or when they are not ours to judge: syntax errors and Hydra's own groups go to Hydra)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    overrides = _override_args(args)
    if not overrides or any(o.startswith("hydra.searchpath") for o in overrides):
        return None  # no overrides, or a search path we do not see: Hydra judges
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException:
        return None
    choices: list[str] = []
    for ov in parsed:
        group = ov.key_or_group.split("@", 1)[0]
        if ov.is_delete() or group.startswith("hydra") or not _group_exists(group):
            continue
        values = list(ov.sweep_string_iterator()) if ov.is_sweep_override() else [ov.get_value_element_as_str()]
        allowed = group_options(group)
        for value in values:
            if value in ("null", "None") or value in allowed:
                continue
            return f"{group}={value} is not an option; allowed: {', '.join(allowed)} (or null)"
        choices.append(f"{'+' if ov.is_add() else ''}{ov.key_or_group}={values[0]}")
    return _check_keys(parsed, choices)


def _compose_or_none(overrides: list[str]) -> Any:
    """The composed config, or None when Hydra cannot compose it (it reports that itself)."""
    from hydra import compose, initialize_config_module

    try:
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            return compose(CONFIG_NAME, overrides=overrides)
    except Exception:  # noqa: BLE001 - Hydra reports composition problems itself
        return None


def _check_keys(parsed: list[Any], choices: list[str]) -> str | None:
    """Unknown keys (``scene.fooo=1`` without ``+``): name the key and list the valid ones; then
    values of the wrong type (``scene.distance_mm=abc``, also in a sweep list), in the words of a
    wrong value.

    One composition with the group choices and the single values when it succeeds (then no
    single-value key is unknown, and value overrides add no keys, so the keys are those of the
    choices alone); only when it fails, a second with the choices alone to name the key."""
    values = [
        ov
        for ov in parsed
        if not ov.is_add()
        and not ov.is_delete()
        and not ov.is_force_add()
        and not ov.key_or_group.startswith("hydra")
        and not _group_exists(ov.key_or_group)
    ]
    keys = [ov.key_or_group for ov in values]
    if not keys:
        return None
    fixed = [f"{ov.key_or_group}={ov.get_value_element_as_str()}" for ov in values if not ov.is_sweep_override()]
    cfg = _compose_or_none([*choices, *fixed])
    if cfg is None:
        base = _compose_or_none(choices)
        return None if base is None else _unknown_key(base, keys)
    return _unknown_key(cfg, keys) or _check_types(cfg, values)


def _unknown_key(cfg: Any, keys: list[str]) -> str | None:
    """The first of ``keys`` that ``cfg`` does not have, as one line naming the allowed ones."""
    from omegaconf import DictConfig, OmegaConf

    for key in keys:
        top = key.split(".", 1)[0]
        if top not in cfg.keys():  # keys() keeps ??? values
            import difflib

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
    from omegaconf import OmegaConf

    from nirspi_pipe.errors import ConfigError
    from nirspi_pipe.pipeline import STAGE_GROUPS, check_types

    runs: list[tuple[Any, tuple[str, ...]]] = [(cfg, ("camera", *STAGE_GROUPS))]
    for ov in values:
        if not ov.is_sweep_override():
            continue
        for value in ov.sweep_iterator():
            one = cfg.copy()
            try:
                OmegaConf.update(one, ov.key_or_group, value, merge=False)
            except Exception:  # noqa: BLE001 - Hydra reports it when it composes the job
                continue
            runs.append((one, (ov.key_or_group.split(".", 1)[0],)))
    for config, groups in runs:
        for group in groups:
            node = config.get(group)
            if node is None:
                continue
            try:
                check_types(node, group)
            except ConfigError as exc:
                return str(exc)
    return None
