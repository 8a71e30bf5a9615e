"""The config catalogue, through Hydra's public API only: which groups and options exist, the
schemas that make the stages' Python signatures the one source of config defaults, and composing
a config (the runner's side; no stage imports this module).

**Defaults live in Python.** The defaults of a config option are the defaults of its ``_target_``
(the dataclass fields, or the signature's parameters). :func:`register_schemas` reads every
option file ``<group>/<option>.yaml`` of a config package whose defaults list names
``/schema/<group>/<option>@_here_`` and announces the node ``schema/<group>/<option>``: every
field of the target with its default (:func:`schema_defaults`), served to Hydra by the config
source :class:`SchemaSource` (public plugin API) and generated when first composed.
The option file then keeps only its ``_target_`` and the values that differ from the target's
defaults (a preset); ``tests/test_config_schema.py`` checks that no option repeats a default.
Types come from the same annotations (:func:`nirspi_pipe.instantiate.check_types`): ``nirspi-run``
checks them before any job starts (:mod:`nirspi_pipe.app.validate`), the runner before it builds a
stage; a wrong type is named by its annotation (``a number``). docs/architecture.md, "Where defaults and
types live", says why the schemas are plain nodes rather than typed structured configs.

Group and option listings go through ``hydra.initialize_config_module`` and the public
:class:`hydra.core.config_loader.ConfigLoader` interface of ``GlobalHydra``; when a Hydra app is
already running (``nirspi-run``) its own global instance is used. The experiments folder and
installed plugins' config folders are on the search path (:func:`nirspi_pipe.app.plugins.activate`
registers a public ``SearchPathPlugin``).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from importlib import resources
from typing import Any

import numpy as np
import yaml
from hydra import compose, initialize_config_module
from hydra.core.config_search_path import ConfigSearchPath
from hydra.core.global_hydra import GlobalHydra
from hydra.core.object_type import ObjectType
from hydra.core.plugins import Plugins
from hydra.plugins.config_source import ConfigLoadError, ConfigResult, ConfigSource
from hydra.plugins.search_path_plugin import SearchPathPlugin
from omegaconf import OmegaConf

from nirspi_pipe.app.plugins import activate, trusted_import_path
from nirspi_pipe.device.recording import RecordingError
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.instantiate import build
from nirspi_pipe.targets import locate, resolve

__all__ = [
    "CONFIG_MODULE",
    "CONFIG_NAME",
    "SCHEMA_GROUP",
    "group_options",
    "config_groups",
    "all_groups",
    "scan_indices",
    "render_scene",
    "locate",
    "schema_defaults",
    "schema_node",
    "register_schemas",
    "schema_reference",
    "SchemaSource",
    "SchemaSearchPath",
]

log = logging.getLogger("nirspi_pipe.app.configs")

#: The package holding the primary config and its groups.
CONFIG_MODULE = "nirspi_pipe.conf"
#: The primary config's name.
CONFIG_NAME = "config"
#: The config group of the generated defaults: ``schema/<group>/<option>`` (:class:`SchemaSource`).
SCHEMA_GROUP = "schema"
#: A dataclass field with ``metadata={CONFIG_FIELD: False}`` is left out of the schema: a field the
#: runner sets (``Recorded.scan_indices``), or one that is not a key of its options unless an
#: option sets it (``LaxFriedrichsSFS.slope_average``: sfs=second_order).
CONFIG_FIELD = "config"


class _NotPlain(TypeError):
    """A default that a config cannot spell (a callable, an arbitrary object)."""


def _plain(value: Any) -> Any:
    """A default as a config value: scalars as they are, tuples as lists, a dataclass instance as
    a node with its ``_target_`` and its own fields (``Photodiode.budget``)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        node: dict[str, Any] = {"_target_": f"{cls.__module__}.{cls.__qualname__}"}
        for f in _config_fields(cls):
            node[f.name] = _plain(getattr(value, f.name))
        return node
    raise _NotPlain(type(value).__name__)


def _config_fields(cls: Any) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if f.init and f.metadata.get(CONFIG_FIELD, True)]


def schema_defaults(target: Any) -> dict[str, Any]:
    """The config node of a ``_target_`` (a class or function, or its dotted path): every
    parameter with its Python default (``???`` when it has none), in signature order. Parameters
    whose default a config cannot spell, and dataclass fields marked
    ``metadata={"config": False}``, are left out. Raises :class:`~nirspi_pipe.errors.ConfigError`
    when a dotted name is not on the allow-list (:mod:`nirspi_pipe.targets`; nothing is imported),
    ``ImportError`` when an allowed one does not import."""
    obj = resolve(target, "_target_") if isinstance(target, str) else target  # allowed, then imported
    if obj is None:
        raise ImportError(f"_target_ {target} does not import")
    items: list[tuple[str, Any]] = []
    if dataclasses.is_dataclass(obj):
        for f in _config_fields(obj):
            if f.default is not dataclasses.MISSING:
                items.append((f.name, f.default))
            elif f.default_factory is not dataclasses.MISSING:
                items.append((f.name, f.default_factory()))
            else:
                items.append((f.name, "???"))
    else:
        kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        for name, p in inspect.signature(obj).parameters.items():
            if p.kind in kinds:
                items.append((name, "???" if p.default is inspect.Parameter.empty else p.default))
    out: dict[str, Any] = {}
    for name, default in items:
        try:
            out[name] = _plain(default)
        except _NotPlain:
            continue
    return out


def schema_reference(group: str, option: str) -> str:
    """The defaults-list entry an option file lists first: ``/schema/<group>/<option>@_here_``."""
    return f"/{SCHEMA_GROUP}/{group}/{option}@_here_"


def _option_files(conf_package: str) -> Iterator[tuple[str, str, Any]]:
    """``(group, option, file)`` of every ``<group>/<option>.yaml`` below a config package."""

    def walk(node: Any, group: str) -> Iterator[tuple[str, str, Any]]:
        for entry in sorted(node.iterdir(), key=lambda e: e.name):
            if entry.is_dir() and not entry.name.startswith(("_", ".")):
                if not group and entry.name in ("hydra", SCHEMA_GROUP):
                    continue
                yield from walk(entry, f"{group}/{entry.name}" if group else entry.name)
            elif group and entry.is_file() and entry.name.endswith(".yaml"):
                yield group, entry.name[: -len(".yaml")], entry

    yield from walk(resources.files(conf_package), "")


def _schema_node(target: str, where: str) -> dict[str, Any]:
    try:
        return schema_defaults(target)
    except Exception as exc:  # noqa: BLE001 - one option's broken target must not stop the others
        log.warning("%s: no schema (%s: %s)", where, type(exc).__name__, exc)
        return {}


def _nested(raw: dict[str, Any], node: dict[str, Any], where: str) -> dict[str, Any]:
    """``node`` (a target's defaults) where the file sets a key to a node of its own: a node with
    a ``_target_`` (``source.effects``) gets that target's defaults, recursively; any other node
    is the file's alone."""
    for key, value in raw.items():
        if isinstance(value, dict) and isinstance(value.get("_target_"), str):
            node[key] = _nested(value, _schema_node(value["_target_"], f"{where}.{key}"), f"{where}.{key}")
        elif isinstance(value, dict):
            node.pop(key, None)
    return node


#: ``{"<group>/<option>": (provider package, the option file's content)}``: the schemas that
#: :func:`register_schemas` announced. Generated on first load (:class:`SchemaSource`), cached.
_SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {}
_GENERATED: dict[str, dict[str, Any]] = {}


def schema_node(name: str) -> dict[str, Any]:
    """The generated schema ``schema/<name>`` (``scene/sphere``; ``camera``), built on first use
    from the option's ``_target_`` (only the options a run composes import their targets)."""
    if name not in _GENERATED:
        _, raw = _SCHEMAS[name]
        _GENERATED[name] = _nested(raw, _schema_node(raw["_target_"], name), name)
    return _GENERATED[name]


def register_schemas(conf_package: str) -> list[str]:
    """Announce ``schema/<group>/<option>`` for every option file of ``conf_package`` (a config
    package: ``nirspi_pipe.conf``, or a plugin's) whose defaults list names it
    (:func:`schema_reference`): the defaults of the option's ``_target_``
    (:func:`schema_defaults`); a key the file sets to a node with a ``_target_`` of its own
    (``source.effects``) gets that target's defaults in turn, so the file keeps only what differs
    (there: the ``${fog}`` interpolations). A node ``<key>`` of the primary config (``camera``)
    gets ``schema/<key>`` when the primary defaults list names ``/schema/<key>@<key>``.

    Hydra reads them through :class:`SchemaSource` (a public ``ConfigSource`` plugin; the
    primary config puts ``nirspi-schema://`` on its ``hydra.searchpath``), which builds each on first load: targets are imported only
    when their option is composed, and nothing is added to Hydra's ``ConfigStore`` (which Hydra
    deep-copies for every composition). A name another package announced is not replaced.
    Returns the names announced."""
    _register_source()
    announced: list[str] = []

    def load(entry: Any) -> dict[str, Any] | None:
        try:
            raw = yaml.safe_load(entry.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError):
            return None  # Hydra reports a broken file when it is composed
        return raw if isinstance(raw, dict) else None

    def listed(raw: dict[str, Any]) -> list[str]:
        return [d for d in raw.get("defaults") or [] if isinstance(d, str)]

    def announce(name: str, raw: dict[str, Any]) -> None:
        if name in _SCHEMAS and _SCHEMAS[name][0] != conf_package:
            log.warning("schema/%s is announced by %s; %s does not replace it", name, _SCHEMAS[name][0], conf_package)
            return
        _SCHEMAS[name] = (conf_package, raw)
        _GENERATED.pop(name, None)
        announced.append(name)

    for group, option, entry in _option_files(conf_package):
        raw = load(entry)
        if raw is not None and isinstance(raw.get("_target_"), str) and schema_reference(group, option) in listed(raw):
            announce(f"{group}/{option}", raw)
    primary = resources.files(conf_package) / f"{CONFIG_NAME}.yaml"
    raw = load(primary) if primary.is_file() else None
    for key, value in (raw or {}).items():
        if isinstance(value, dict) and isinstance(value.get("_target_"), str):
            if f"/{SCHEMA_GROUP}/{key}@{key}" in listed(raw or {}):
                announce(str(key), value)
    return announced


def _register_source() -> None:
    """Register :class:`SchemaSource` (the scheme ``nirspi-schema://``) and
    :class:`SchemaSearchPath` with Hydra's public ``Plugins.register`` (idempotent). Done when
    this module is imported, so that a search path replaced on the command line
    (``hydra.searchpath=[…]``) keeps the schemas; the primary config lists the source too, for a
    composition whose search path was made before this module was imported."""
    with trusted_import_path():  # Hydra's first scan of hydra_plugins: never the working directory (issue 32)
        Plugins.instance().register(SchemaSource)
        Plugins.instance().register(SchemaSearchPath)


class SchemaSource(ConfigSource):
    """Hydra config source ``nirspi-schema://``: serves ``schema/<group>/<option>`` from
    :func:`schema_node`. It holds no configs itself (Hydra deep-copies its sources for every
    composition), and it lists nothing at the top level, so ``schema`` is not shown as a group."""

    @staticmethod
    def scheme() -> str:
        return "nirspi-schema"

    def _name(self, config_path: str) -> str | None:
        path = config_path.strip("/")
        path = path[: -len(".yaml")] if path.endswith(".yaml") else path
        return path[len(SCHEMA_GROUP) + 1 :] if path.startswith(f"{SCHEMA_GROUP}/") else None

    def load_config(self, config_path: str) -> ConfigResult:
        name = self._name(config_path)
        if name is None or name not in _SCHEMAS:
            raise ConfigLoadError(f"schema not found: {config_path}")
        return ConfigResult(
            config=OmegaConf.create(schema_node(name)),
            path=f"{self.scheme()}://{self.path}",
            provider=_SCHEMAS[name][0],
            header={"package": None},  # as a ConfigStore entry: the package the defaults list gives (_here_)
        )

    def available(self) -> bool:
        return True

    def is_group(self, config_path: str) -> bool:
        path = config_path.strip("/")
        if path == SCHEMA_GROUP:
            return True
        name = self._name(path)
        return name is not None and any(k.startswith(name + "/") for k in _SCHEMAS)

    def is_config(self, config_path: str) -> bool:
        name = self._name(config_path)
        return name is not None and name in _SCHEMAS

    def list(self, config_path: str, results_filter: ObjectType | None) -> list[str]:
        path = config_path.strip("/")
        if path != SCHEMA_GROUP and not path.startswith(SCHEMA_GROUP + "/"):
            return []  # not at the top level: the schemas are not config groups of their own
        prefix = path[len(SCHEMA_GROUP) + 1 :]
        prefix = f"{prefix}/" if prefix else ""
        out: set[str] = set()
        for key in _SCHEMAS:
            if key.startswith(prefix):
                head, _, rest = key[len(prefix) :].partition("/")
                if rest and results_filter in (None, ObjectType.GROUP):
                    out.add(head)
                elif not rest and results_filter in (None, ObjectType.CONFIG):
                    out.add(head)
        return sorted(out)


class SchemaSearchPath(SearchPathPlugin):
    """Appends :class:`SchemaSource` to every Hydra search path made after this module is
    imported (registered by :func:`_register_source`)."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="nirspi-schema", path=f"{SchemaSource.scheme()}://{CONFIG_MODULE}")


_register_source()


@contextmanager
def _loader() -> Iterator[Any]:
    """Hydra's public config loader, initialising Hydra on our config module when no app runs."""
    activate()  # plugin config folders join the search path
    gh = GlobalHydra.instance()
    if gh.is_initialized():
        yield gh.config_loader()
        return
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        yield GlobalHydra.instance().config_loader()


@lru_cache(maxsize=1)
def _catalogue() -> dict[str, tuple[str, ...]]:
    """``{group: options}`` of every config group (nested ones as ``parent/child``), read once.

    Read from the loader's config sources (``ConfigLoader.get_sources``, ``ConfigSource.list``:
    Hydra's plugin interface), the union over sources as Hydra's ``get_group_options`` takes it;
    that call deep-copies the whole config repository each time, and the catalogue's 49 calls
    took 0.83 s of CPU against 0.05 s from the sources, the same ``{group: options}``, measured
    in one process after a composition (issue 41: the check's cost in a default run)."""
    found: dict[str, tuple[str, ...]] = {}
    with _loader() as loader:
        sources = loader.get_sources()

        def options(group: str, kind: ObjectType) -> list[str]:
            out: set[str] = set()
            for source in sources:
                if source.is_group(group):
                    out.update(source.list(group, kind))
            return sorted(out)

        def walk(parent: str) -> None:
            for g in options(parent, ObjectType.GROUP):
                path = f"{parent}/{g}" if parent else g
                if path in ("hydra", SCHEMA_GROUP):
                    continue
                found[path] = tuple(options(path, ObjectType.CONFIG))
                walk(path)

        walk("")
    return found


def group_options(group: str) -> list[str]:
    """Options of a config group (``scan`` → ``["basic", …]``), plugins included."""
    return list(_catalogue().get(group, ()))


def config_groups(parent: str = "") -> list[str]:
    """Config groups directly under ``parent`` (top level by default), Hydra's own excluded."""
    prefix = f"{parent}/" if parent else ""
    return sorted(g[len(prefix) :] for g in _catalogue() if g.startswith(prefix) and "/" not in g[len(prefix) :])


def all_groups() -> frozenset[str]:
    """Every config group, nested ones as ``parent/child``, Hydra's own excluded."""
    return frozenset(_catalogue())


def scan_indices(order: str, ratio: float, n: int) -> np.ndarray:
    """Indices of the scan option ``order`` (``conf/scan/<order>.yaml``, plugins included) at
    ``ratio`` for ``n × n`` patterns: what a recording that names its order was measured with.
    Raises :class:`~nirspi_pipe.device.recording.RecordingError` naming ``order`` when it is not
    an option. Handed to the recorded source by the runner."""
    allowed = group_options("scan")
    if order not in allowed:
        raise RecordingError("order", f"{order!r} is not a scan option; allowed: {', '.join(allowed)}")
    with _loader():
        cfg = compose(CONFIG_NAME, overrides=[f"scan={order}", f"scan.ratio={float(ratio)!r}"])
    return np.asarray(build(cfg.scan, "scan").select(n), dtype=np.int64)


def render_scene(scene: str, resolution: int, overrides: list[str] | None = None) -> np.ndarray:
    """Relative radiance ``(n, n)`` of the ``scene=<scene>`` option at ``resolution`` (for the
    device emulator's command line). Raises :class:`ConfigError` naming ``scene`` and the
    allowed options when ``scene`` is not one."""
    allowed = group_options("scene")
    if scene not in allowed:
        raise ConfigError("scene", scene, ", ".join(allowed))

    with _loader():
        cfg = compose(CONFIG_NAME, overrides=[f"scene={scene}", f"camera.resolution={resolution}", *(overrides or [])])
    camera = build(cfg.camera, "camera")
    return build(cfg.scene, "scene").render(camera).radiance
