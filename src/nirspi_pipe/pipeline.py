"""Build the stages from a composed config and run them, timing each one.

The runner owns all timing (``time.perf_counter`` around each stage call) and all randomness
(one ``SeedSequence`` from ``cfg.seed``, one independent child stream per random stage, so that
switching a stage on does not change another stage's noise).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from omegaconf import DictConfig

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.stages import Products
from nirspi_pipe.targets import check_targets, locate, resolve
from nirspi_pipe.types import Camera

__all__ = ["STAGE_GROUPS", "RunOutput", "build", "build_stages", "check_types", "run_pipeline"]

#: Config groups in pipeline order. ``camera`` is a plain node, not a group.
STAGE_GROUPS = (
    "scene",
    "source",
    "scan",
    "solver",
    "upscale",
    "sfs",
    "itof",
    "fusion",
    "surface",
    "metrics",
)

#: Independent random streams, by stage. Append only: the position fixes the stream.
_RNG_STREAMS = ("source", "itof")

T = TypeVar("T")


@dataclass
class RunOutput:
    """What one run produced: its products, metrics, per-stage times and bookkeeping."""

    products: Products
    metrics: dict[str, float]
    timings_ms: dict[str, float]
    derived: dict[str, float]
    info: dict[str, dict[str, Any]]
    warnings: list[str] = field(default_factory=list)


#: Config groups that are built inside another node (``source.effects.fog: ${fog}``): an error
#: there is reported under the group the user typed (``fog.beta_per_m``).
EFFECT_GROUPS = ("fog", "illumination", "detector")
_EFFECT_PARENT = "source.effects."


def _user_key(full_key: str | None, key: str) -> tuple[str, bool]:
    """Where to report an error of node ``full_key`` built as part of group ``key``: the path the
    user types, and whether it is absolute (an effect group inside ``source.effects``)."""
    if not full_key:
        return key, False
    if full_key.startswith(_EFFECT_PARENT) and full_key[len(_EFFECT_PARENT) :].split(".")[0] in EFFECT_GROUPS:
        return full_key[len(_EFFECT_PARENT) :], True
    return (full_key, False) if full_key.startswith(key + ".") else (key, False)


class _BuildFailure(Exception):
    """A stage constructor raised while building the node at ``path`` (the innermost one)."""

    def __init__(self, inner: BaseException, path: str, node: dict[str, Any]) -> None:
        super().__init__(str(inner))
        self.inner, self.path, self.node = inner, path, node


#: Keys of a ``_target_`` node that are not constructor arguments (Hydra's ``instantiate`` keys).
_RESERVED = ("_target_", "_recursive_", "_partial_", "_convert_", "_args_")


def _instantiate(node: Any, path: str) -> Any:
    """``hydra.utils.instantiate(node, _convert_="all")`` for a resolved plain container: every
    dict with a ``_target_`` becomes ``target(**children)`` (``_recursive_: false`` passes the
    children as they are, ``_partial_: true`` gives a ``functools.partial``), other dicts and lists
    stay plain. Written out because Hydra's ``instantiate`` cost 57-62 ms per job on the
    paper's table3 config (it copies and re-resolves the node in OmegaConf), against under 1 ms
    here, timing both on the ten stage nodes of one composed job (a sweep ran beside it); a paper sweep builds
    432 jobs. ``tests/test_config.py`` builds every shipped option through it."""
    if isinstance(node, list):
        return [_instantiate(v, f"{path}.{i}") for i, v in enumerate(node)]
    if not isinstance(node, dict):
        return node
    recursive = node.get("_recursive_", True) is not False
    kwargs = {
        str(k): (_instantiate(v, f"{path}.{k}") if recursive else v) for k, v in node.items() if k not in _RESERVED
    }
    target = node.get("_target_")
    if target is None:
        return kwargs
    try:
        fn = resolve(target, f"{path}._target_")  # the allow-list (nirspi_pipe.targets), then the import
        if fn is None:
            raise ImportError(f"Error locating target '{target}': no such module or attribute")
        args = [
            (_instantiate(v, f"{path}._args_.{i}") if recursive else v) for i, v in enumerate(node.get("_args_", []))
        ]
        if node.get("_partial_", False):
            import functools

            return functools.partial(fn, *args, **kwargs)
        return fn(*args, **kwargs)
    except _BuildFailure:
        raise
    except Exception as exc:  # noqa: BLE001 - translated by build()
        raise _BuildFailure(exc, path, node) from exc


def build(node: Any, key: str) -> Any:
    """Instantiate one config node (``_target_``) recursively, turning errors into one-line
    messages. ``node`` is a config node or its resolved plain container.

    A :class:`ConfigError` raised by the stage is re-raised with its key prefixed by the node it
    came from, so the user sees ``scene.reflectance=1.5 is not allowed; allowed: …`` (and
    ``fog.beta_per_m=…`` for the fog model that ``source.effects`` builds).
    """
    from omegaconf import Container, OmegaConf

    plain = OmegaConf.to_container(node, resolve=True) if isinstance(node, Container) else node
    check_targets(plain, key)  # every target of the node is allowed, before anything is imported
    check_types(plain, key)
    try:
        return _instantiate(plain, key)
    except _BuildFailure as failure:
        inner = failure.inner
        where, absolute = _user_key(failure.path, key)
        if isinstance(inner, ConfigError):
            err = inner.under(where)
            raise (
                ConfigError(err.key, err.value, err.allowed, err.unknown_key, absolute=True) if absolute else err
            ) from None
        if isinstance(inner, TypeError) and "unexpected keyword argument" in str(inner):
            bad = str(inner).rsplit("'", 2)[-2] if str(inner).count("'") >= 2 else "?"
            raise ConfigError(f"{where}.{bad}", None, _accepted_keys(failure.node), unknown_key=True) from None
        raise inner from None


_KINDS = {float: "a number", int: "an integer", bool: "true or false", str: "a string"}


def _scalar_kinds(hint: Any) -> tuple[type, ...] | None:
    """The scalar types a field annotation accepts (None also when Optional), or None when the
    annotation is not a plain scalar (tuples, mappings, models: the stage checks those)."""
    import types
    import typing

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


def _allowed_for(cls: Any, params: dict[str, Any], name: str, kinds: tuple[type, ...]) -> str:
    """The ``allowed`` text the stage itself gives for ``name``: its ``__post_init__`` is asked
    with a value of the right type that no range accepts (NaN), so a wrong type and a wrong
    value read the same."""
    fallback = " or ".join(_KINDS[k] for k in kinds if k in _KINDS) + (", or null" if type(None) in kinds else "")
    if float not in kinds and int not in kinds:
        return fallback
    try:
        cls(**{**params, name: float("nan")})
    except ConfigError as exc:
        if exc.key == name:
            return exc.allowed
    except Exception:  # noqa: BLE001 - only a message is asked for
        pass
    return fallback


def check_types(node: Any, key: str) -> None:
    """Scalar fields of every ``_target_`` dataclass in ``node`` (a config node or its resolved
    plain container) have their annotated type; a string for a number
    (``scene.distance_mm=abc``) is a one-line :class:`ConfigError` naming the key and the stage's
    allowed values. The dataclass annotations are the source of types."""
    import dataclasses
    import inspect
    import typing

    from omegaconf import Container, OmegaConf

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
        fn = resolve(target, f"{path}._target_")  # allowed before it is imported
        if fn is None:
            return
        try:
            hints = typing.get_type_hints(fn)
            if dataclasses.is_dataclass(fn):
                names = [f.name for f in dataclasses.fields(fn) if f.init]
            else:
                names = [p for p in inspect.signature(fn).parameters if p in hints]
        except Exception:  # noqa: BLE001 - unresolvable annotations: instantiation reports problems
            return
        for name in names:
            if name not in sub:
                continue
            kinds = _scalar_kinds(hints.get(name))
            if kinds is None or _type_ok(sub[name], kinds):
                continue
            params = {str(k): v for k, v in sub.items() if not str(k).startswith("_")}
            where, _ = _user_key(f"{path}.{name}", key)
            raise ConfigError(where, sub[name], _allowed_for(fn, params, name, kinds), absolute=True)

    try:
        walk(OmegaConf.to_container(node, resolve=True) if isinstance(node, Container) else node, key)
    except ConfigError:
        raise
    except Exception:  # noqa: BLE001 - the check is a courtesy; instantiation reports the rest
        return


def _accepted_keys(node: Any) -> str:
    """Comma-separated constructor parameters of a node's ``_target_`` (for error messages)."""
    import inspect

    try:
        params = inspect.signature(locate(str(node.get("_target_")))).parameters
    except Exception:  # noqa: BLE001 - best effort for a message
        return "see the group's config file"
    return ", ".join(p for p in params if p not in ("self", "args", "kwargs"))


def build_stages(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """Instantiate every enabled stage group of ``cfg`` (absent or null groups are skipped)."""
    stages: dict[str, Any] = {}
    for group in STAGE_GROUPS:
        node = cfg.get(group)
        if node is not None:
            stages[group] = build(node, group)
    return stages


class _Clock:
    def __init__(self) -> None:
        self.ms: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.ms[name] = (time.perf_counter() - t0) * 1e3

    def call(self, name: str, fn: Callable[..., T], *args: Any) -> T:
        """Time ``fn(*args)`` as stage ``name``; its ConfigErrors get the group prefix."""
        with self.stage(name):
            try:
                return fn(*args)
            except ConfigError as exc:
                raise exc.under(name) from None


def _measure_itof(stage: Any, image: Any, grid: Camera, truth: Any, acq: Any, rng: np.random.Generator) -> Any:
    """Aim steerable iToF spots with the 2D image when the stage can (``aimed``), then measure."""
    if hasattr(stage, "aimed"):
        stage = stage.aimed(image, grid)
    return stage.measure(truth, acq, rng)


@contextmanager
def _recorded_warnings() -> Iterator[list[warnings.WarningMessage]]:
    """Record every warning; an exception leaving the block carries them as ``nirspi_warnings``
    (a failed record keeps the warnings that explain it)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield caught  # type: ignore[misc]
        except Exception as exc:
            exc.nirspi_warnings = [f"{w.category.__name__}: {w.message}" for w in caught]  # type: ignore[attr-defined]
            raise


def _stage_info(products: Products) -> dict[str, dict[str, Any]]:
    pairs: dict[str, Any] = {
        "source": products.acquisition,
        "solver": products.image,
        "upscale": products.upscaled,
        "sfs": products.depth,
        "itof": products.itof,
        "fusion": products.cloud,
        "surface": products.mesh,
    }
    return {k: dict(v.info) for k, v in pairs.items() if v is not None and v.info}


def effective_seed(cfg: DictConfig | Mapping[str, Any]) -> int:
    """The run's seed: ``cfg.seed``, or when it is null a seed derived from the hash of the
    resolved config (so every job of a sweep gets its own, reproducible noise)."""
    from omegaconf import Container, OmegaConf

    from nirspi_pipe.records import config_hash

    seed = cfg.get("seed", 0)
    if seed is None:
        resolved: Any = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, Container) else cfg
        return int(config_hash(resolved)[:8], 16)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", seed, "an integer >= 0, or null (derived from the config)")
    return seed


def run_pipeline(cfg: DictConfig | Mapping[str, Any]) -> RunOutput:
    """Run one configuration end to end and return its products, metrics and timings (ms).
    ``cfg`` is a composed config or its resolved plain container (what the nirspi launcher runs:
    turning it back into an OmegaConf node would cost ~40 ms per job).

    Raises :class:`ConfigError` / :class:`NirspiError` for bad configuration or input; other
    exceptions are bugs or numerical failures and propagate unchanged.
    """
    from nirspi_pipe.scene.render import forget_renders

    forget_renders()  # ground truths rendered by the metrics are shared within this run only
    seed = effective_seed(cfg)
    streams = dict(zip(_RNG_STREAMS, np.random.SeedSequence(seed).spawn(len(_RNG_STREAMS)), strict=False))
    rngs = {k: np.random.default_rng(s) for k, s in streams.items()}

    clock = _Clock()
    with _recorded_warnings() as caught:
        with clock.stage("build"):
            camera: Camera = build(cfg["camera"], "camera")
            stages = build_stages(cfg)
        for required in ("source", "scan", "solver"):
            if required not in stages:
                raise ConfigError(required, "null", f"a {required} stage ({required}=null is not allowed)")
        source, scan, solver = stages["source"], stages["scan"], stages["solver"]
        if getattr(source, "needs_scan_indices", False) and getattr(source, "scan_indices", None) is None:
            from dataclasses import replace

            from nirspi_pipe.configs import scan_indices

            source = replace(source, scan_indices=scan_indices)  # the runner resolves scan options
        n = camera.resolution

        truth = None
        if source.needs_scene:
            if "scene" not in stages:
                raise ConfigError("scene", "null", "a scene (this source simulates one)")
            truth = clock.call("scene", stages["scene"].render, camera)
        indices = clock.call("scan", scan.select, n)
        acq = clock.call("source", source.acquire, truth, indices, n, rngs["source"])
        truth = acq.truth if acq.truth is not None else truth
        image = clock.call("solver", solver.solve, acq)

        upscaled = depth = itof = cloud = mesh = None
        if "upscale" in stages:
            upscaled = clock.call("upscale", stages["upscale"].upscale, image)
        # 3D stages work on the finest image; their camera is that image's grid.
        shaded = upscaled if upscaled is not None else image
        grid = camera if shaded.data.shape[0] == n else camera.resampled(shaded.data.shape[0])
        if "sfs" in stages:
            depth = clock.call("sfs", stages["sfs"].solve, shaded, grid)
        if "itof" in stages:
            itof = clock.call("itof", _measure_itof, stages["itof"], shaded, grid, truth, acq, rngs["itof"])
        if "fusion" in stages:
            if depth is None:
                raise ConfigError("fusion", cfg.get("fusion"), "null unless an sfs stage is set")
            cloud = clock.call("fusion", stages["fusion"].fuse, depth, itof, grid)
        if "surface" in stages:
            if cloud is None:
                raise ConfigError("surface", cfg.get("surface"), "null unless a fusion stage is set")
            mesh = clock.call("surface", stages["surface"].reconstruct, cloud)

        products = Products(truth, acq, image, upscaled, depth, itof, cloud, mesh)
        metrics: dict[str, float] = {}
        if "metrics" in stages:
            metrics = clock.call("metrics", stages["metrics"].compute, products)
    timings = dict(clock.ms)
    timings["total"] = float(sum(v for k, v in clock.ms.items() if k != "build"))
    info = _stage_info(products)
    info.setdefault("run", {})["seed"] = seed
    return RunOutput(
        products=products,
        metrics={k: float(v) for k, v in metrics.items()},
        timings_ms=timings,
        derived={k: v for k, v in acq.derived.items()},
        info=info,
        warnings=[f"{w.category.__name__}: {w.message}" for w in caught],
    )
