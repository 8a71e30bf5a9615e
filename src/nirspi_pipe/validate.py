"""Check command-line overrides before Hydra composes them, so that an unknown option gives one
line naming the group and its allowed values instead of Hydra's multi-line report."""

from __future__ import annotations

from nirspi_pipe.configs import CONFIG_MODULE, CONFIG_NAME, all_groups, config_groups, group_options

__all__ = ["check_overrides", "group_options", "config_groups"]

#: Hydra flags followed by a value.
_FLAGS_WITH_VALUE = {
    "-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir",
    "-c", "--cfg", "-p", "--package", "--experimental-rerun", "-sc", "--shell-completion",
}


def _group_exists(group: str) -> bool:
    return group in all_groups()


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


def _check_keys(parsed: list, choices: list[str]) -> str | None:  # type: ignore[type-arg]
    """Unknown keys (``scene.fooo=1`` without ``+``): name the key and list the valid ones."""
    from hydra import compose, initialize_config_module
    from omegaconf import DictConfig, OmegaConf

    keys = [
        ov.key_or_group
        for ov in parsed
        if not ov.is_add() and not ov.is_delete() and not ov.is_force_add()
        and not ov.key_or_group.startswith("hydra") and not _group_exists(ov.key_or_group)
    ]
    if not keys:
        return None
    try:
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            cfg = compose(CONFIG_NAME, overrides=choices)
    except Exception:  # noqa: BLE001 - Hydra reports composition problems itself
        return None
    for key in keys:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if isinstance(node, DictConfig) and leaf not in node.keys():  # keys() keeps ??? values
            where = parent or "the top level"
            known = ", ".join(sorted(str(k) for k in node if str(k) != "_target_"))
            return f"{key} is not a key of {where}; allowed keys: {known} (or +{key}=... to add one)"
    return None
