"""Composition for the entry check (:mod:`nirspi_pipe.app.entry`): the configuration Hydra
will compose, with Hydra's public compose API, the same config name and the same overrides Hydra
gets; a configuration that does not compose is refused (one line), never handed on. Also the
reference compositions (Hydra's node with the ``hydra/…`` choices only, cached per process), the
default search path, and the override parser the checks share.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.object_type import ObjectType
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode
from omegaconf import OmegaConf

from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME
from nirspi_pipe.app.flags import Refused
from nirspi_pipe.errors import yaml_problem
from nirspi_pipe.safeio import short_repr

__all__ = [
    "baseline",
    "check_filled_by_hydra",
    "compose_config",
    "default_choices",
    "default_searchpath",
    "hydra_group_options",
    "one_line",
    "parse_override_cached",
    "parse_overrides",
    "primary_exists",
    "short_value",
]


def one_line(text: object, limit: int = 300) -> str:
    return " ".join(str(text).split())[:limit]


def short_value(value: Any, limit: int = 80) -> str:
    return short_repr(value, limit)


def parse_overrides(overrides: list[str]) -> list[Any]:
    parser = OverridesParser.create()
    out = []
    for text in overrides:
        try:
            out.append(parser.parse_override(text))
        except Exception as exc:  # noqa: BLE001 - a syntax error is refused here, not handed on
            first = str(exc).strip().splitlines()
            raise Refused(f"{text[:80]!r} is not a valid override: {one_line(first[0] if first else exc)}") from None
    return out


@lru_cache(maxsize=4096)
def parse_override_cached(text: str) -> Any:
    """:func:`parse_overrides` of one override, cached: a sweep's jobs repeat the same overrides."""
    return parse_overrides([text])[0]


def compose_config(config_name: str, overrides: list[str]) -> Any:
    """The configuration Hydra will compose (``return_hydra_config``), or :class:`Refused`.

    What Hydra fills itself (``hydra.overrides``, ``hydra.runtime``) is checked to be exactly what
    it fills from ``overrides`` (:func:`check_filled_by_hydra`): Hydra re-applies
    ``hydra.overrides.hydra`` to every sweep job and sweeps ``hydra.overrides.task``, so a list a
    config brings there would run unchecked."""
    user_folder = any(ov.key_or_group == "hydra.searchpath" for ov in parse_overrides(overrides))
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
            f"the configuration does not compose: {one_line(text[0] if text else type(exc).__name__)}"
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


def _check_overrides_node(got: Any, overrides: list[str]) -> None:
    """``hydra.overrides`` exactly what Hydra fills from ``overrides``: ``hydra`` the input lines
    of the Hydra overrides, ``task`` the others, in order."""
    parsed = parse_overrides(overrides)
    want = {
        "hydra": [ov.input_line for ov in parsed if ov.is_hydra_override()],
        "task": [ov.input_line for ov in parsed if not ov.is_hydra_override()],
    }
    if not isinstance(got, dict) or set(got) != set(want) or any(got[k] != want[k] for k in want):
        extra = [str(v) for k in want for v in (got.get(k) or []) if v not in want[k]] if isinstance(got, dict) else []
        shown = f" (it holds {short_value(extra[0])})" if extra else ""
        raise Refused(
            f"hydra.overrides differs from the command line{shown}: it is not allowed in a config or an "
            "override; allowed: Hydra fills it from the command line (set each key by its own override)"
        )


def _check_runtime_node(runtime: Any, known_choices: dict[str, Any] | None) -> None:
    """``hydra.runtime``: only Hydra's own keys, its ``output_dir`` unset, and no group choice
    outside ``known_choices`` (when given)."""
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


def check_filled_by_hydra(
    hydra_node: dict[str, Any], overrides: list[str], known_choices: dict[str, Any] | None = None
) -> None:
    """:class:`Refused` unless ``hydra.overrides`` and ``hydra.runtime`` of a composed node are
    exactly what Hydra fills from ``overrides``: ``overrides.hydra`` the input lines of the Hydra
    overrides, ``overrides.task`` the others, in order; ``runtime`` only Hydra's own keys, its
    ``output_dir`` unset, and (``known_choices``: Hydra's defaults list) no group choice that
    Hydra did not make."""
    _check_overrides_node(hydra_node.get("overrides") or {}, overrides)
    _check_runtime_node(hydra_node.get("runtime") or {}, known_choices)


@lru_cache(maxsize=8)
def baseline(choices: tuple[tuple[str, str | None], ...]) -> dict[str, Any]:
    """Hydra's node composed from the default config and search path, with the given
    ``hydra/…`` choices only (unresolved, as plain containers). Cached per process."""
    overrides = [f"{g}={'null' if o is None else o}" for g, o in choices]
    cfg = compose_config(CONFIG_NAME, overrides)
    return OmegaConf.to_container(cfg.hydra, resolve=False)  # type: ignore[return-value]


def default_choices() -> dict[str, str | None]:
    return dict(baseline(()).get("runtime", {}).get("choices", {}))


def hydra_group_options(group: str) -> list[str]:
    """Options of a Hydra group (``hydra/launcher``) on the default search path; also inside a
    running app (a job's gate), whose Hydra is set aside and restored as in :func:`compose_config` (the
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


def primary_exists(name: str) -> bool:
    """Whether ``name`` is a primary config on the default search path (a ``-cd`` folder joins
    Hydra's search path as a ``hydra.searchpath`` entry, after the primary config is chosen)."""
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return bool(GlobalHydra.instance().config_loader().get_sources()) and any(
            src.is_config(name) for src in GlobalHydra.instance().config_loader().get_sources()
        )


def default_searchpath() -> list[str]:
    """``hydra.searchpath`` of the primary config (conf/config.yaml)."""
    return [str(p) for p in baseline(()).get("searchpath", [])]
