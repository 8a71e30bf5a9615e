"""Build a stage from its config node: Hydra's ``instantiate`` semantics for a resolved node,
restricted to the allow-list of :mod:`nirspi_pipe.targets`, with one-line errors naming the key.

Used by the runner (:mod:`nirspi_pipe.pipeline`) and by the config layer
(:func:`nirspi_pipe.app.configs.scan_indices`). It imports nothing of Hydra or OmegaConf: it works
on plain data, and :func:`plain_config` turns any mapping that reads as a config (an OmegaConf
node included, whose interpolations resolve as they are read) into that plain data.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from functools import lru_cache
from typing import Any

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.targets import check_once, find_targets, locate

__all__ = ["EFFECT_GROUPS", "Plan", "accepted_keys", "build", "check_types", "plain_config", "user_key"]


#: Config groups that are built inside another node (``source.effects.fog: ${fog}``): an error
#: there is reported under the group the user typed (``fog.beta_per_m``).
EFFECT_GROUPS = ("fog", "illumination", "detector")
_EFFECT_PARENT = "source.effects."


def plain_config(node: Any) -> Any:
    """``node`` as plain data: every mapping a ``dict`` with ``str`` keys, every list or tuple
    (or other non-string sequence, such as an OmegaConf ``ListConfig``) a ``list``, scalars
    unchanged. A mapping's values are read through its own ``items()``, so an OmegaConf node's
    interpolations are resolved here, as ``OmegaConf.to_container(node, resolve=True)`` does
    (tested against it in tests/test_architecture.py). Plain data comes back as an equal copy."""
    if isinstance(node, Mapping):
        return {str(k): plain_config(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)) or (isinstance(node, Sequence) and not isinstance(node, (str, bytes))):
        return [plain_config(v) for v in node]
    return node


def user_key(full_key: str | None, key: str) -> tuple[str, bool]:
    """Where to report an error of node ``full_key`` built as part of group ``key``: the path the
    user types, and whether it is absolute (an effect group inside ``source.effects``)."""
    if not full_key:
        return key, False
    if full_key.startswith(_EFFECT_PARENT) and full_key[len(_EFFECT_PARENT) :].split(".")[0] in EFFECT_GROUPS:
        return full_key[len(_EFFECT_PARENT) :], True
    return (full_key, False) if full_key.startswith(key + ".") else (key, False)


class Plan(Mapping[str, Any]):
    """One job's resolved configuration as plain data, converted once (:meth:`of`), whose
    ``_target_`` strings are checked against the allow-list before anything is imported
    (:meth:`check`: one walk) and whose classes are imported once (:meth:`resolve`).

    The front ends make it at the boundary (the app from its composed config; the runner from
    whatever it is handed, when that is not a plan already); :func:`build` and
    :func:`check_types` take it, so building a job's stages neither converts its nodes again
    nor checks a target again (issue 42: before, one default job through
    :func:`nirspi_pipe.execute.execute_job` made 28 conversions, 60 allow-list checks and 40
    imports by string for its 24 targets; now 1 conversion, one check per distinct target
    string and one import per class: tests/test_one_plan.py). Checks go through
    :func:`nirspi_pipe.targets.check_once`: a string that passed against the same allow-list
    earlier in the process (the app's check of the same config before launching, the schema
    catalogue's, an earlier job of a sweep) is not compared again. A plan owns its ``config``:
    nothing changes it after it is made. It reads as the mapping it holds (so
    :func:`plain_config` of a plan is a copy of its config)."""

    __slots__ = ("_checked", "_classes", "config", "path")

    def __init__(self, config: Any, path: str = "") -> None:
        self.config = config  # plain data (plain_config's), not copied
        self.path = path
        self._checked: frozenset[Any] | None = None
        self._classes: dict[str, Any] = {}

    def __getitem__(self, key: str) -> Any:
        return self.config[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.config)

    def __len__(self) -> int:
        return len(self.config)

    @classmethod
    def of(cls, cfg: Any, path: str = "") -> Plan:
        """``cfg`` itself when it is a plan, else a plan of ``cfg`` as plain data (one conversion,
        :func:`plain_config`; an OmegaConf node's interpolations resolve here)."""
        return cfg if isinstance(cfg, Plan) else cls(plain_config(cfg), path)

    def check(self) -> Plan:
        """Every target of the plan against the allow-list (:func:`nirspi_pipe.targets.check_once`
        on each place :func:`nirspi_pipe.targets.find_targets` names, as ``check_targets``),
        the first time it is called; a refusal is the one-line :class:`ConfigError` naming its
        key (the first place the string appears)."""
        if self._checked is None:
            found = set()
            for key, target in find_targets(self.config, self.path):  # one walk, as check_targets
                check_once(target, key)
                found.add(target)
            self._checked = frozenset(found)
        return self

    def resolve(self, target: Any, key: str) -> Any:
        """:func:`nirspi_pipe.targets.resolve` with this plan's checks: a target :meth:`check` passed
        is not checked again (any other is, first: :func:`nirspi_pipe.targets.check_once`); each
        class is imported once per plan."""
        if self._checked is None or not isinstance(target, str) or target not in self._checked:
            check_once(target, key)
        name = str(target)
        if name not in self._classes:
            self._classes[name] = locate(name)
        return self._classes[name]


class _BuildFailure(Exception):
    """A stage constructor raised while building the node at ``path`` (the innermost one)."""

    def __init__(self, inner: BaseException, path: str, node: dict[str, Any]) -> None:
        super().__init__(str(inner))
        self.inner, self.path, self.node = inner, path, node


#: Keys of a ``_target_`` node that are not constructor arguments (Hydra's ``instantiate`` keys).
_RESERVED = ("_target_", "_recursive_", "_partial_", "_convert_", "_args_")


def _instantiate(node: Any, path: str, plan: Plan) -> Any:
    """``hydra.utils.instantiate(node, _convert_="all")`` for a resolved plain container: every
    dict with a ``_target_`` becomes ``target(**children)`` (``_recursive_: false`` passes the
    children as they are, ``_partial_: true`` gives a ``functools.partial``), other dicts and lists
    stay plain. Written out because Hydra's ``instantiate`` cost 57-62 ms per job on the
    paper's table3 config (it copies and re-resolves the node in OmegaConf), against under 1 ms
    here, timing both on the ten stage nodes of one composed job (a sweep ran beside it); a paper sweep builds
    432 jobs. ``tests/test_config.py`` builds every shipped option through it."""
    if isinstance(node, list):
        return [_instantiate(v, f"{path}.{i}", plan) for i, v in enumerate(node)]
    if not isinstance(node, dict):
        return node
    recursive = node.get("_recursive_", True) is not False
    kwargs = {
        str(k): (_instantiate(v, f"{path}.{k}", plan) if recursive else v)
        for k, v in node.items()
        if k not in _RESERVED
    }
    target = node.get("_target_")
    if target is None:
        return kwargs
    try:
        fn = plan.resolve(target, f"{path}._target_")  # the allow-list (nirspi_pipe.targets), then the import
        if fn is None:
            raise ImportError(f"Error locating target '{target}': no such module or attribute")
        args = [
            (_instantiate(v, f"{path}._args_.{i}", plan) if recursive else v)
            for i, v in enumerate(node.get("_args_", []))
        ]
        if node.get("_partial_", False):
            return functools.partial(fn, *args, **kwargs)
        return fn(*args, **kwargs)
    except _BuildFailure:
        raise
    except Exception as exc:  # translated by build()
        raise _BuildFailure(exc, path, node) from exc


def build(node: Any, key: str, plan: Plan | None = None) -> Any:
    """Instantiate one config node (``_target_``) recursively, turning errors into one-line
    messages. ``node`` is a config node or its resolved plain container; with ``plan``, it is a
    node of ``plan.config`` (plain already), and its targets are those the plan checked: it is
    neither converted nor checked again. Without, it is converted and its targets checked once.

    A :class:`ConfigError` raised by the stage is re-raised with its key prefixed by the node it
    came from, so the user sees ``scene.reflectance=1.5 is not allowed; allowed: …`` (and
    ``fog.beta_per_m=…`` for the fog model that ``source.effects`` builds).
    """
    if plan is None:
        plan = Plan.of(node, key)
        node = plan.config
    plan.check()  # every target of the plan is allowed, before anything is imported (once per plan)
    check_types(node, key, plan)
    try:
        return _instantiate(node, key, plan)
    except _BuildFailure as failure:
        inner = failure.inner
        where, absolute = user_key(failure.path, key)
        if isinstance(inner, ConfigError):
            err = inner.under(where)
            raise (
                ConfigError(err.key, err.value, err.allowed, err.unknown_key, absolute=True) if absolute else err
            ) from None
        if isinstance(inner, TypeError) and "unexpected keyword argument" in str(inner):
            bad = str(inner).rsplit("'", 2)[-2] if str(inner).count("'") >= 2 else "?"
            raise ConfigError(f"{where}.{bad}", None, accepted_keys(failure.node), unknown_key=True) from None
        raise inner from None


_KINDS = {float: "a number", int: "an integer", bool: "true or false", str: "a string"}


def _scalar_kinds(hint: Any) -> tuple[type, ...] | None:
    """The scalar types a field annotation accepts (None also when Optional), or None when the
    annotation is not a plain scalar (tuples, mappings, models: the stage checks those)."""
    args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    kinds = tuple(a for a in args if a in _KINDS or a is type(None))
    return kinds if kinds and len(kinds) == len(args) else None


def _type_ok(value: Any, kinds: tuple[type, ...]) -> bool:
    if value is None:
        return type(None) in kinds
    if isinstance(value, bool):
        return bool in kinds
    if isinstance(value, (int, float)):
        return float in kinds or (int in kinds and float(value).is_integer())
    return isinstance(value, str) and str in kinds


def _type_text(kinds: tuple[type, ...]) -> str:
    """What a field annotated with ``kinds`` accepts, in words (``a number, or null``)."""
    return " or ".join(_KINDS[k] for k in kinds if k in _KINDS) + (", or null" if type(None) in kinds else "")


@lru_cache(maxsize=256)
def _scalar_fields(fn: Any) -> tuple[tuple[str, tuple[type, ...] | None], ...]:
    """``(name, scalar kinds or None)`` of a target's constructor fields, read from its annotations
    once per class (``typing.get_type_hints`` on every node cost ~3 ms per sweep job)."""
    hints = typing.get_type_hints(fn)
    if dataclasses.is_dataclass(fn):
        names = [f.name for f in dataclasses.fields(fn) if f.init]
    else:
        names = [p for p in inspect.signature(fn).parameters if p in hints]
    return tuple((name, _scalar_kinds(hints.get(name))) for name in names)


def check_types(node: Any, key: str, plan: Plan | None = None) -> None:
    """Scalar fields of every ``_target_`` class in ``node`` (a config node or its resolved plain
    container) have their annotated type; a string for a number (``scene.distance_mm=abc``) is a
    one-line :class:`ConfigError` naming the key and the annotated type (``a number``). The
    annotations are the source of types; a value of the right type is judged by the stage's own
    range check when it is built. With ``plan``, ``node`` is a node of ``plan.config`` (plain, its
    targets checked and imported through the plan). Targets must be allowed (:func:`nirspi_pipe.targets.check_targets`);
    a target whose annotations cannot be read raises ``TypeError`` naming it (a bug of the target,
    not of the config)."""

    def walk(sub: Any, path: str) -> None:
        if isinstance(sub, list):
            for i, item in enumerate(sub):
                walk(item, f"{path}.{i}")
            return
        if not isinstance(sub, dict):
            return
        for k, v in sub.items():
            if not str(k).startswith("_"):
                walk(v, f"{path}.{k!s}")
        target = sub.get("_target_")
        if not isinstance(target, str):
            return
        fn = checked.resolve(target, f"{path}._target_")  # allowed before it is imported
        if fn is None:
            return  # not importable: building it says so, naming the key
        try:
            fields = _scalar_fields(fn)
        except Exception as exc:
            raise TypeError(f"{path}._target_={target}: its annotations cannot be read: {exc}") from exc
        for name, kinds in fields:
            if name in sub and kinds is not None and not _type_ok(sub[name], kinds):
                where, _ = user_key(f"{path}.{name}", key)
                raise ConfigError(where, sub[name], _type_text(kinds), absolute=True)

    if plan is None:
        plan = Plan.of(node, key)
        node = plan.config
    checked = plan
    walk(node, key)


def accepted_keys(node: Any) -> str:
    """Comma-separated constructor parameters of a node's ``_target_`` (for error messages)."""
    try:
        params = inspect.signature(locate(str(node.get("_target_")))).parameters
    except Exception:  # noqa: BLE001 - best effort for a message
        return "see the group's config file"
    return ", ".join(p for p in params if p not in ("self", "args", "kwargs"))
