"""Plugin discovery: installed packages that add stage implementations and their configs.

A plugin is a separately installed distribution that declares an entry point in the group
``nirspi_pipe.plugins`` (see docs/plugins.md)::

    [project.entry-points."nirspi_pipe.plugins"]
    admm = "nirspi_admm"              # a module with a SEARCHPATH attribute, or
    admm = "nirspi_admm:register"     # a callable returning the search path(s)

Loading an entry point gives either

* a **callable**: it is called with no arguments; it may register dataclass configs in Hydra's
  ``ConfigStore`` and returns ``None``, one config folder (``"pkg://nirspi_admm.conf"``) or a
  list of them; or
* a **module**: its ``SEARCHPATH`` attribute (a string or a list of strings, optional) names the
  config folder(s); importing it may register ``ConfigStore`` entries as a side effect.

A config folder holds ``<group>/<option>.yaml`` files (``solver/admm_tv.yaml``) whose
``_target_`` names the plugin's class. nirspi-pipe appends every folder to Hydra's config search
path by registering one :class:`NirspiPluginSearchPath` (a Hydra ``SearchPathPlugin``)
programmatically, so it does not depend on the ``hydra_plugins`` namespace package (which
breaks with editable installs, Hydra issue #2359). Options of nirspi-pipe itself come first on
the search path: a plugin cannot shadow a built-in option (``--plugins`` reports the clash).

A plugin that fails to load (import error, exception in its register function, a search path
that does not resolve) is reported by name with one warning line and skipped; other plugins and
the run itself go on.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from importlib import metadata
from types import ModuleType
from typing import Any

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

__all__ = [
    "ENTRY_POINT_GROUP",
    "PluginInfo",
    "PluginFailure",
    "PluginReport",
    "discover",
    "activate",
    "search_paths",
    "format_report",
    "NirspiPluginSearchPath",
]

log = logging.getLogger("nirspi_pipe.plugins")

#: The entry-point group plugins declare themselves in.
ENTRY_POINT_GROUP = "nirspi_pipe.plugins"

#: Provider name prefix of plugin folders on Hydra's search path.
_PROVIDER = "nirspi-plugin"


@dataclass(frozen=True)
class PluginInfo:
    """One plugin that loaded: its entry point, its config folders and what they add.

    Attributes:
        name: entry-point name.
        value: entry-point value (``module`` or ``module:attr``).
        distribution: ``name version`` of the installed distribution, when known.
        searchpath: config folders it added to Hydra's search path.
        options: ``{group: [option, …]}`` from its config folders and ``ConfigStore`` entries.
        shadowed: ``group/option`` names also defined by nirspi-pipe (the built-in one wins).
    """

    name: str
    value: str
    distribution: str
    searchpath: tuple[str, ...]
    options: dict[str, list[str]] = field(default_factory=dict)
    shadowed: tuple[str, ...] = ()


@dataclass(frozen=True)
class PluginFailure:
    """A plugin that could not be loaded, with a one-line reason."""

    name: str
    value: str
    error: str


@dataclass(frozen=True)
class PluginReport:
    """Result of discovering all installed plugins."""

    plugins: tuple[PluginInfo, ...]
    failures: tuple[PluginFailure, ...]

    @property
    def searchpath(self) -> tuple[str, ...]:
        """All plugin config folders, in discovery order."""
        return tuple(p for info in self.plugins for p in info.searchpath)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _store_options() -> set[tuple[str, str]]:
    """``(group, option)`` pairs currently in Hydra's ConfigStore (nested groups joined by /)."""
    from hydra.core.config_store import ConfigStore

    out: set[tuple[str, str]] = set()

    def walk(node: dict[str, Any], prefix: str) -> None:
        for key, value in node.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}/{key}" if prefix else key)
            elif prefix and key.endswith(".yaml"):
                out.add((prefix, key[: -len(".yaml")]))

    walk(ConfigStore.instance().repo, "")
    return out


def _as_paths(value: Any, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        return (value,)
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise TypeError(f"{where} must be None, a string or a list of strings, got {type(value).__name__}")


def _folder_options(path: str) -> dict[str, list[str]]:
    """``{group: [options]}`` of one config folder (raises when the folder does not resolve)."""
    from hydra._internal.config_repository import ConfigRepository
    from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
    from hydra.core.object_type import ObjectType

    csp = ConfigSearchPathImpl()
    csp.append(_PROVIDER, path)
    repo = ConfigRepository(config_search_path=csp)
    source = repo.get_sources()[0]
    if not source.available():
        raise FileNotFoundError(f"config folder {path} does not exist")
    found: dict[str, list[str]] = {}

    def walk(group: str) -> None:
        for sub in repo.get_group_options(group, ObjectType.GROUP):
            walk(f"{group}/{sub}" if group else sub)
        if group:
            opts = repo.get_group_options(group, ObjectType.CONFIG)
            if opts:
                found[group] = sorted(opts)

    walk("")
    return found


def _builtin_options() -> set[tuple[str, str]]:
    from hydra._internal.config_repository import ConfigRepository
    from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
    from hydra.core.object_type import ObjectType

    csp = ConfigSearchPathImpl()
    csp.append("main", "pkg://nirspi_pipe.conf")
    repo = ConfigRepository(config_search_path=csp)
    return {
        (g, o)
        for g in repo.get_group_options("", ObjectType.GROUP)
        for o in repo.get_group_options(g, ObjectType.CONFIG)
    }


def _distribution(ep: metadata.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "?"
    return f"{dist.metadata['Name']} {dist.version}"


def _load_one(ep: metadata.EntryPoint, builtin: set[tuple[str, str]]) -> PluginInfo:
    before = _store_options()
    obj = ep.load()
    if isinstance(obj, ModuleType):
        paths = _as_paths(getattr(obj, "SEARCHPATH", None), f"{ep.value}.SEARCHPATH")
    elif callable(obj):
        paths = _as_paths(obj(), f"{ep.value}()")
    else:
        raise TypeError(f"{ep.value} is neither a module nor a callable")
    options: dict[str, set[str]] = {}
    for group, opt in _store_options() - before:
        options.setdefault(group, set()).add(opt)
    for path in paths:
        for group, opts in _folder_options(path).items():
            options.setdefault(group, set()).update(opts)
    shadowed = tuple(sorted(f"{g}/{o}" for g, opts in options.items() for o in opts if (g, o) in builtin))
    return PluginInfo(
        name=ep.name,
        value=ep.value,
        distribution=_distribution(ep),
        searchpath=paths,
        options={g: sorted(o) for g, o in sorted(options.items())},
        shadowed=shadowed,
    )


_REPORT: PluginReport | None = None


def discover(refresh: bool = False) -> PluginReport:
    """Load every entry point of :data:`ENTRY_POINT_GROUP` once per process and report.

    A plugin that raises while loading is logged (one warning line naming it) and listed in
    :attr:`PluginReport.failures`; it never propagates. ``refresh`` loads them again (tests).
    """
    global _REPORT
    if _REPORT is not None and not refresh:
        return _REPORT
    from hydra.core.plugins import Plugins

    Plugins.instance()  # registers Hydra's config sources (pkg://, file://) on first use
    builtin = _builtin_options()
    plugins: list[PluginInfo] = []
    failures: list[PluginFailure] = []
    seen: set[str] = set()
    eps = sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)
    for ep in eps:
        if ep.name in seen:  # the same distribution found twice on sys.path
            continue
        seen.add(ep.name)
        try:
            plugins.append(_load_one(ep, builtin))
        except (Exception, SystemExit) as exc:  # noqa: BLE001 - a broken plugin must not break the run
            failure = PluginFailure(ep.name, ep.value, _one_line(exc))
            failures.append(failure)
            log.warning("plugin %r (%s) failed to load and was skipped: %s", ep.name, ep.value, failure.error)
    _REPORT = PluginReport(tuple(plugins), tuple(failures))
    return _REPORT


def search_paths() -> tuple[str, ...]:
    """Config folders of the loaded plugins (loads them on first use)."""
    return discover().searchpath


class NirspiPluginSearchPath(SearchPathPlugin):
    """Appends the config folders of installed nirspi-pipe plugins to Hydra's search path."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        for info in discover().plugins:
            for path in info.searchpath:
                search_path.append(f"{_PROVIDER}:{info.name}", path)


def activate() -> PluginReport:
    """Load the plugins and register :class:`NirspiPluginSearchPath` with Hydra (idempotent).

    Call it before composing a config (``nirspi-run`` does); afterwards every Hydra search path
    created in this process (the app's, :mod:`nirspi_pipe.validate`'s, ``compose`` in tests)
    includes the plugin config folders. Joblib workers receive the composed configuration and
    Hydra's singleton state (ConfigStore, plugin registry) from the parent.
    """
    from hydra.core.plugins import Plugins

    report = discover()
    Plugins.instance().register(NirspiPluginSearchPath)
    return report


def format_report(report: PluginReport) -> str:
    """Human-readable listing for ``nirspi-run --plugins``."""
    lines = [f"nirspi-pipe plugins (entry-point group {ENTRY_POINT_GROUP!r}):"]
    if not report.plugins and not report.failures:
        lines.append("  none installed")
    for info in report.plugins:
        lines.append(f"  {info.name}  [{info.distribution}]  {info.value}")
        for path in info.searchpath:
            lines.append(f"    configs: {path}")
        for group, opts in info.options.items():
            lines.append(f"    {group}: {', '.join(opts)}")
        if not info.options:
            lines.append("    (adds no config options)")
        for name in info.shadowed:
            lines.append(f"    shadowed by the built-in option {name} (rename it in the plugin)")
    for fail in report.failures:
        lines.append(f"  {fail.name}  FAILED ({fail.value}): {fail.error}")
    return "\n".join(lines)
