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
breaks with editable installs, Hydra issue #2359).

A plugin whose config names clash with a built-in option (a file or a ``ConfigStore`` entry
``scan/basic``) is refused whole, named, and its ``ConfigStore`` entries are removed again, so
nothing of it shadows or merges into a built-in config. A plugin that fails to load (any
exception on import or in its register function, ``SystemExit`` and ``KeyboardInterrupt``
included; a search path that does not resolve) is reported by name with one warning line and
skipped. On POSIX each plugin is first imported in a forked child, so one that ends the process
(``os._exit``) or hangs on import is skipped the same way. Other plugins and the run go on.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata, resources
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from hydra.core.config_search_path import ConfigSearchPath
from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
from hydra.plugins.search_path_plugin import SearchPathPlugin

from nirspi_pipe.targets import installed, trusted_paths, untrusted

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

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

#: nirspi-pipe's experiment configs (``+experiment=…``).
EXPERIMENTS_PATH = "pkg://nirspi_pipe.experiments"

_BUILTIN_CONF = "nirspi_pipe.conf"

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
    """

    name: str
    value: str
    distribution: str
    searchpath: tuple[str, ...]
    options: dict[str, list[str]] = field(default_factory=dict)


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
    #: ``(name, origin)`` of entry points outside the installed distributions: never loaded
    ignored: tuple[tuple[str, str], ...] = ()

    @property
    def searchpath(self) -> tuple[str, ...]:
        """All plugin config folders, in discovery order."""
        return tuple(p for info in self.plugins for p in info.searchpath)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _store_options() -> set[tuple[str, str]]:
    """``(group, option)`` pairs currently in Hydra's ConfigStore (nested groups joined by /)."""
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


def _folder(path: str) -> Traversable:
    """The config folder ``pkg://package.sub`` or ``file://dir`` (a plain path is a file path)."""
    if path.startswith("pkg://"):
        module = path[len("pkg://") :].strip("/").replace("/", ".")
        try:
            return resources.files(module)
        except ModuleNotFoundError as exc:
            raise FileNotFoundError(f"config folder {path} does not exist ({exc})") from None
    return Path(path[len("file://") :] if path.startswith("file://") else path)


def _folder_options(path: str) -> dict[str, list[str]]:
    """``{group: [options]}`` of one config folder (raises when the folder does not resolve):
    ``<group>/<option>.yaml`` files, nested groups joined by ``/``."""
    root = _folder(path)
    if not root.is_dir():
        raise FileNotFoundError(f"config folder {path} does not exist")
    found: dict[str, list[str]] = {}

    def walk(node: Traversable, group: str) -> None:
        for entry in node.iterdir():
            if entry.is_dir() and not entry.name.startswith(("_", ".")):
                walk(entry, f"{group}/{entry.name}" if group else entry.name)
            elif group and entry.is_file() and entry.name.endswith((".yaml", ".yml")):
                found.setdefault(group, []).append(entry.name.rsplit(".", 1)[0])

    walk(root, "")
    return {g: sorted(o) for g, o in sorted(found.items())}


_BUILTIN_STORE: frozenset[tuple[str, str]] | None = None


def _builtin_options() -> set[tuple[str, str]]:
    """``(group, option)`` of nirspi-pipe's own configs and ConfigStore entries (before plugins)."""
    global _BUILTIN_STORE
    if _BUILTIN_STORE is None:  # taken once, before any plugin registered anything
        _BUILTIN_STORE = frozenset(_store_options())
    builtin = {(g, o) for g, opts in _folder_options(f"pkg://{_BUILTIN_CONF}").items() for o in opts}
    return builtin | _BUILTIN_STORE


def _distribution(ep: metadata.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "?"
    return f"{dist.metadata['Name']} {dist.version}"


def _unregister(entries: set[tuple[str, str]]) -> None:
    """Remove ConfigStore entries (``(group, option)``) a refused plugin registered."""
    repo = ConfigStore.instance().repo
    for group, opt in entries:
        node = repo
        for part in group.split("/"):
            node = node.get(part, {})
        node.pop(f"{opt}.yaml", None)


def _register(ep: metadata.EntryPoint) -> tuple[str, ...]:
    """Import the plugin (and call it when it is a callable); its config folders."""
    obj = ep.load()
    if isinstance(obj, ModuleType):
        return _as_paths(getattr(obj, "SEARCHPATH", None), f"{ep.value}.SEARCHPATH")
    if callable(obj):
        return _as_paths(obj(), f"{ep.value}()")
    raise TypeError(f"{ep.value} is neither a module nor a callable")


#: Seconds a plugin may take to import in the guarded probe before it is skipped as hung.
PROBE_TIMEOUT_S = 60.0


def _probe(ep: metadata.EntryPoint) -> str | None:
    """Import the plugin once in a forked child first (POSIX): a plugin that ends the process on
    import (``os._exit``, a signal) or hangs is caught here and skipped, instead of ending
    ``nirspi-run`` silently. Returns the reason to skip it, or None. Exceptions (including
    ``SystemExit``/``KeyboardInterrupt``) are left to the real import, which reports them."""
    if not hasattr(os, "fork"):
        return None
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: import, say so, and leave without running any exit handler
        os.close(read_fd)
        try:
            _register(ep)
        except BaseException:  # noqa: BLE001 - the parent's own import reports it
            pass
        os.write(write_fd, b"ok")
        os._exit(0)
    os.close(write_fd)
    try:
        deadline = time.monotonic() + PROBE_TIMEOUT_S
        data = b""
        while time.monotonic() < deadline:
            ready, _, _ = select.select([read_fd], [], [], max(deadline - time.monotonic(), 0.0))
            if not ready:
                break
            chunk = os.read(read_fd, 16)
            if not chunk:
                break
            data += chunk
        if data != b"ok":
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            _, status = os.waitpid(pid, 0)
            if os.WIFEXITED(status):
                return f"ended the process on import (exit status {os.WEXITSTATUS(status)}, os._exit?)"
            sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
            if sig == signal.SIGKILL and not data:
                return f"did not finish importing within {PROBE_TIMEOUT_S:g} s"
            return f"killed the process on import (signal {sig})"
        os.waitpid(pid, 0)
        return None
    finally:
        os.close(read_fd)


def _load_one(ep: metadata.EntryPoint, builtin: set[tuple[str, str]]) -> PluginInfo:
    reason = _probe(ep)
    if reason:
        raise PluginRefused(reason)
    before = _store_options()
    paths = _register(ep)
    added = _store_options() - before
    options: dict[str, set[str]] = {}
    for group, opt in added:
        options.setdefault(group, set()).add(opt)
    try:
        for path in paths:
            for group, opts in _folder_options(path).items():
                options.setdefault(group, set()).update(opts)
    except BaseException:
        _unregister(added)
        raise
    clashes = sorted(f"{g}/{o}" for g, opts in options.items() for o in opts if (g, o) in builtin)
    if clashes:  # refused whole: nothing of it shadows or merges into a built-in config
        _unregister(added)
        raise PluginRefused(f"its config name(s) {', '.join(clashes)} clash with built-in ones; rename them")
    return PluginInfo(
        name=ep.name,
        value=ep.value,
        distribution=_distribution(ep),
        searchpath=paths,
        # its generated schemas (schema/<group>/<option>, nirspi_pipe.app.configs) are not options
        options={g: sorted(o) for g, o in sorted(options.items()) if g.split("/", 1)[0] != "schema"},
    )


class PluginRefused(Exception):
    """A plugin that loaded but is not used (a clash with a built-in name, or a process exit)."""


_REPORT: PluginReport | None = None


def discover(refresh: bool = False) -> PluginReport:
    """Load every entry point of :data:`ENTRY_POINT_GROUP` once per process and report.

    A plugin that raises while loading is logged (one warning line naming it) and listed in
    :attr:`PluginReport.failures`; it never propagates. ``refresh`` loads them again (tests).
    """
    global _REPORT
    if _REPORT is not None and not refresh:
        return _REPORT

    Plugins.instance()  # registers Hydra's config sources (pkg://, file://) on first use
    builtin = _builtin_options()
    plugins: list[PluginInfo] = []
    failures: list[PluginFailure] = []
    seen: set[str] = set()

    eps = sorted((e for e in metadata.entry_points(group=ENTRY_POINT_GROUP) if installed(e)), key=lambda e: e.name)
    for ep in eps:
        if ep.name in seen:  # the same distribution found twice on sys.path
            continue
        seen.add(ep.name)
        try:
            plugins.append(_load_one(ep, builtin))
        except BaseException as exc:  # noqa: BLE001 - a broken plugin must not break the run (SystemExit,
            # KeyboardInterrupt raised by its import included; the process exits are caught by _probe)
            failure = PluginFailure(ep.name, ep.value, _one_line(exc))
            failures.append(failure)
            log.warning("plugin %r (%s) failed to load and was skipped: %s", ep.name, ep.value, failure.error)
    ignored = tuple(sorted(untrusted(ENTRY_POINT_GROUP).items()))
    for name, where in ignored:
        log.warning(
            "plugin %r was ignored: its entry point is outside the installed distributions (%s); "
            "plugins come only from installed distributions (pip install it)",
            name,
            where,
        )
    _REPORT = PluginReport(tuple(plugins), tuple(failures), ignored)
    return _REPORT


def search_paths() -> tuple[str, ...]:
    """Config folders of the loaded plugins (loads them on first use)."""
    return discover().searchpath


class NirspiPluginSearchPath(SearchPathPlugin):
    """Appends the config folders of installed nirspi-pipe plugins to Hydra's search path."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        # the experiments folder (conf/config.yaml names it in hydra.searchpath too; listing it
        # here lets the config catalogue see it without composing the primary config)
        search_path.append("nirspi-pipe", EXPERIMENTS_PATH)
        for info in discover().plugins:
            for path in info.searchpath:
                search_path.append(f"{_PROVIDER}:{info.name}", path)


def activate() -> PluginReport:
    """Load the plugins and register :class:`NirspiPluginSearchPath` with Hydra (idempotent).

    Call it before composing a config (``nirspi-run`` does); afterwards every Hydra search path
    created in this process (the app's, :mod:`nirspi_pipe.app.validate`'s, ``compose`` in tests)
    includes the plugin config folders. Joblib workers receive the composed configuration and
    Hydra's singleton state (ConfigStore, plugin registry) from the parent.
    """
    with trusted_import_path():  # Hydra's first scan of hydra_plugins: never the working directory
        Plugins.instance()
        report = discover()
        Plugins.instance().register(NirspiPluginSearchPath)
    return report


@contextmanager
def trusted_import_path() -> Iterator[None]:
    """``sys.path`` without the working directory and relative entries while plugins load
    (:func:`nirspi_pipe.targets.trusted_paths`): Hydra imports every module of the
    ``hydra_plugins`` namespace it finds on ``sys.path`` on its first use, and ``python -c`` or a
    notebook puts the working directory there. Restored afterwards."""
    saved = list(sys.path)
    sys.path[:] = trusted_paths()
    try:
        yield
    finally:
        sys.path[:] = saved


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
    for fail in report.failures:
        lines.append(f"  {fail.name}  FAILED ({fail.value}): {fail.error}")
    for name, where in report.ignored:
        lines.append(f"  {name}  IGNORED: not from an installed distribution ({where})")
    return "\n".join(lines)
