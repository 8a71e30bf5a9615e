"""Build the stages from a resolved config (plain data) and run them, timing each one.

The runner owns all timing (``time.perf_counter`` around each stage call) and all randomness
(one ``SeedSequence`` from ``cfg.seed``, one independent child stream per random stage, so that
switching a stage on does not change another stage's noise).
"""

from __future__ import annotations

import re
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError, NumericalError
from nirspi_pipe.instantiate import EFFECT_GROUPS, Plan, build, check_types, plain_config
from nirspi_pipe.jobkey import config_hash
from nirspi_pipe.scene.render import forget_renders
from nirspi_pipe.stages import (
    Aimable,
    Itof,
    NeedsScene,
    Products,
    ReadsScanOptions,
    RunStages,
    ScanIndices,
    ScoresWithStages,
    check_stage,
)
from nirspi_pipe.types import Acquisition, Camera, Image2D, Mesh, PointCloud

__all__ = [
    "EFFECT_GROUPS",
    "MODEL_OF_NOTHING",
    "STAGE_GROUPS",
    "Plan",
    "RunOutput",
    "build",
    "build_stages",
    "check_types",
    "run_pipeline",
]

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

#: What to write instead of ``group=null`` for the groups of the simulated medium and detector:
#: they are models the source is built with, not stages of the pipeline, so their "nothing" is a
#: model of nothing (clear air, no background light, a noise-free detector), one spelling each;
#: ``null`` (and ``off``, which ``nirspi-run`` rewrites it to) is refused with this hint.
#: (Stages switch off with ``null`` only: docs/architecture.md, "Switching a stage off".)
MODEL_OF_NOTHING = {
    "fog": "fog=none (clear air)",
    "illumination": "illumination=none (no background light)",
    "detector": "detector=ideal (noise-free)",
}

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


def build_stages(cfg: Mapping[str, Any], plan: Plan | None = None) -> dict[str, Any]:
    """Instantiate every enabled stage group of ``cfg`` (absent or null groups are skipped), each
    checked against its group's protocol (:func:`nirspi_pipe.stages.check_stage`). With ``plan``,
    ``cfg`` is ``plan.config`` and the stages are built from the plan (:func:`build`)."""
    stages: dict[str, Any] = {}
    for group in STAGE_GROUPS:
        node = cfg.get(group)
        if node is not None:
            stages[group] = build(node, group, plan)
            check_stage(group, stages[group], node.get("_target_") if isinstance(node, Mapping) else None)
    return stages


#: numpy's floating-point error warnings ("overflow encountered in multiply", "invalid value
#: encountered in subtract", "divide by zero encountered in log10"). Code that means to make an
#: Inf or NaN says so with ``np.errstate`` (or a warnings filter), which emits none of these.
_FP_WARNING = re.compile(r"(overflow|invalid value|divide by zero) encountered in ")

#: What each product must hold only finite numbers in, by type (its array fields). Left out on
#: purpose: Scene (depth is Inf off the object), DepthMap (NaN outside its mask), ItofSample
#: (sigma is Inf for a spot without a return).
_FINITE_FIELDS: tuple[tuple[type, tuple[str, ...]], ...] = (
    (Acquisition, ("y_pos", "y_neg")),
    (Image2D, ("data",)),
    (PointCloud, ("points_m",)),
    (Mesh, ("vertices_m",)),
)


def _where(w: warnings.WarningMessage) -> str:
    parts = str(w.filename).replace("\\", "/").split("/")
    return f"{'/'.join(parts[-2:])}:{w.lineno}"


def _fp_errors(caught: list[warnings.WarningMessage]) -> list[warnings.WarningMessage]:
    return [w for w in caught if issubclass(w.category, RuntimeWarning) and _FP_WARNING.match(str(w.message))]


def _fp_summary(errors: list[warnings.WarningMessage]) -> str:
    """One phrase for a stage's floating-point errors: the first, where, and how many more."""
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    first = " ".join(str(errors[0].message).split())
    return f"the stage's arithmetic left float64's range: {first} at {_where(errors[0])}{more}"


def _nonfinite_output(out: Any) -> str | None:
    """``field (k of n values NaN or Inf)`` for the first product field of ``out`` that holds a
    non-finite number, else None."""
    for kind, names in _FINITE_FIELDS:
        if isinstance(out, kind):
            for name in names:
                a = getattr(out, name, None)
                if isinstance(a, np.ndarray) and a.dtype.kind in "fc":
                    bad = int(np.count_nonzero(~np.isfinite(a)))
                    if bad:
                        return f"{type(out).__name__}.{name} ({bad} of {a.size} values NaN or Inf)"
    return None


class _Clock:
    """Times each stage; with the run's recorded warnings (``caught``) it is also the safety net
    for numbers: a stage whose arithmetic left float64's range, or whose product holds a NaN or
    an Inf, fails the job with a :class:`NumericalError` naming the stage, never status ok."""

    def __init__(self, caught: list[warnings.WarningMessage] | None = None) -> None:
        self.ms: dict[str, float] = {}
        self.caught = caught if caught is not None else []

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.ms[name] = (time.perf_counter() - t0) * 1e3

    def call(self, name: str, fn: Callable[..., T], *args: Any) -> T:
        """Time ``fn(*args)`` as stage ``name``; its ConfigErrors get the group prefix; a numpy
        floating-point error it raised (as a RuntimeWarning), an ``OverflowError`` or a product
        holding NaN/Inf becomes a :class:`NumericalError` naming the stage."""
        seen = len(self.caught)
        with self.stage(name):
            try:
                out = fn(*args)
            except ConfigError as exc:
                raise exc.under(name) from None
            except (OverflowError, FloatingPointError) as exc:
                raise NumericalError(
                    name, f"the stage's arithmetic left float64's range ({type(exc).__name__}: {exc})"
                ) from exc
            except NirspiError:
                raise
            except Exception as exc:  # a failure that follows a floating-point error is that error's
                first = _fp_errors(self.caught[seen:])
                if not first:
                    raise
                raise NumericalError(
                    name, f"{_fp_summary(first)}, then {type(exc).__name__}: {str(exc).strip()[:200]}"
                ) from exc
        errors = _fp_errors(self.caught[seen:])
        if errors:
            raise NumericalError(name, f"{_fp_summary(errors)}; its result is not a finite number")
        bad = _nonfinite_output(out)
        if bad is not None:
            raise NumericalError(name, f"the stage's result {bad}")
        return out


def _measure_itof(stage: Itof, image: Any, grid: Camera, truth: Any, acq: Any, rng: np.random.Generator) -> Any:
    """Aim steerable iToF spots with the 2D image when the stage can (:class:`Aimable`), then measure."""
    if isinstance(stage, Aimable):
        stage = stage.aimed(image, grid)
    return stage.measure(truth, acq, rng)


def _solve_from_scene(stage: Any, scene_model: Any, truth: Any, image: Any, grid: Camera) -> Any:
    """An SFS stage that reads the scene (the oracle ``sfs=truth``): the truth rendered for the
    SFS grid (the camera's, or the upscaled image's)."""
    if truth is not None and truth.depth_m.shape == (grid.resolution, grid.resolution):
        scene = truth
    elif scene_model is not None and truth is not None:
        scene = scene_model.render(grid)
    else:
        raise ConfigError(
            "sfs", "truth", "an SFS model (sfs=truth reads the simulated scene's depth; this source has none)"
        )
    return stage.solve(image, grid, scene)


@contextmanager
def _recorded_warnings() -> Iterator[list[warnings.WarningMessage]]:
    """Record every warning; an exception leaving the block carries them as ``nirspi_warnings``
    (a failed record keeps the warnings that explain it)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield caught
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


def effective_seed(cfg: Mapping[str, Any]) -> int:
    """The run's seed: ``cfg.seed``, or when it is null a seed derived from the hash of the
    resolved config (so every job of a sweep gets its own, reproducible noise)."""
    seed = cfg.get("seed", 0)
    if seed is None:
        return int(config_hash(cfg if isinstance(cfg, dict) else plain_config(cfg))[:8], 16)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", seed, "an integer >= 0, or null (derived from the config)")
    return seed


def run_pipeline(cfg: Mapping[str, Any] | Plan, *, scan_indices: ScanIndices | None = None) -> RunOutput:
    """Run one configuration end to end and return its products, metrics and timings (ms).
    ``cfg`` is the job's :class:`~nirspi_pipe.instantiate.Plan`, or its resolved config as plain
    data (any mapping that reads as one works), converted here once into a plan. Each
    ``_target_`` is checked against the allow-list once, before the first stage is built, and
    the stages are built from the plan without converting or checking again. ``scan_indices(order, ratio, n)`` resolves the scan option
    a recording names in its pattern spec; the config layer passes
    :func:`nirspi_pipe.app.configs.scan_indices`. A source that needs it and gets none fails
    with a one-line error naming ``source``.

    Raises :class:`ConfigError` / :class:`NirspiError` for bad configuration or input; other
    exceptions are bugs or numerical failures and propagate unchanged.
    """
    forget_renders(files_only=True)  # a scene read from a file is rendered afresh by each run
    plan = Plan.of(cfg)  # one conversion, unless the caller made the plan
    config: Mapping[str, Any] = plan.config
    seed = effective_seed(config)
    streams = dict(zip(_RNG_STREAMS, np.random.SeedSequence(seed).spawn(len(_RNG_STREAMS)), strict=False))
    rngs = {k: np.random.default_rng(s) for k, s in streams.items()}

    _refuse_null_models(config)
    with _recorded_warnings() as caught:
        clock = _Clock(caught)
        camera, stages = _build_all(plan, clock)
        source, scan, solver = _required_stages(stages, scan_indices)
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
        upscaled = clock.call("upscale", stages["upscale"].upscale, image) if "upscale" in stages else None
        products = _run_3d(config, stages, clock, camera, rngs, Products(truth, acq, image, upscaled))
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


def _refuse_null_models(config: Mapping[str, Any]) -> None:
    """A model of the simulated camera (fog, light, detector) set to null is refused: it is not a
    stage that can be switched off."""
    for group, nothing in MODEL_OF_NOTHING.items():
        if group in config and config[group] is None:
            raise ConfigError(group, "null", f"{nothing}; {group} is a model of the simulated camera, not a stage")


def _build_all(plan: Plan, clock: _Clock) -> tuple[Camera, dict[str, Any]]:
    """The camera and every stage of the plan, timed as ``build``; every target checked once,
    before anything is imported. A metrics stage that scores with the run's stages
    (:class:`ScoresWithStages`) gets the ones built here: each stage is built once."""
    with clock.stage("build"):
        plan.check()
        camera: Camera = build(plan.config["camera"], "camera", plan)
        stages = build_stages(plan.config, plan)
        if isinstance(stages.get("metrics"), ScoresWithStages):
            wired = RunStages(stages.get("scene"), stages.get("source"), stages.get("upscale"))
            stages["metrics"] = stages["metrics"].with_stages(wired)
    return camera, stages


def _required_stages(stages: dict[str, Any], scan_indices: ScanIndices | None) -> tuple[Any, Any, Any]:
    """The source, scan and solver (each required), the source given the caller's scan-option
    resolver when it reads scan options and has none."""
    for required in ("source", "scan", "solver"):
        if required not in stages:
            raise ConfigError(required, "null", f"a {required} stage ({required}=null is not allowed)")
    source, scan, solver = stages["source"], stages["scan"], stages["solver"]
    if isinstance(source, ReadsScanOptions) and source.scan_indices is None:
        source = source.with_scan_indices(scan_indices)  # the caller resolves scan options
    return source, scan, solver


def _run_3d(
    config: Mapping[str, Any],
    stages: dict[str, Any],
    clock: _Clock,
    camera: Camera,
    rngs: dict[str, np.random.Generator],
    products: Products,
) -> Products:
    """The 3D stages (sfs, itof, fusion, surface) on the finest image, each where configured;
    ``products`` holds the 2D ones and comes back with the 3D ones filled in."""
    truth, acq, image, upscaled = products.truth, products.acquisition, products.image, products.upscaled
    depth = itof = cloud = mesh = None
    # 3D stages work on the finest image; their camera is that image's grid.
    shaded = upscaled if upscaled is not None else image
    n = camera.resolution
    grid = camera if shaded.data.shape[0] == n else camera.resampled(shaded.data.shape[0])
    if "sfs" in stages and isinstance(stages["sfs"], NeedsScene) and stages["sfs"].needs_scene:
        depth = clock.call("sfs", _solve_from_scene, stages["sfs"], stages.get("scene"), truth, shaded, grid)
    elif "sfs" in stages:
        depth = clock.call("sfs", stages["sfs"].solve, shaded, grid)
    if "itof" in stages:
        itof = clock.call("itof", _measure_itof, stages["itof"], shaded, grid, truth, acq, rngs["itof"])
    if "fusion" in stages:
        if depth is None:
            raise ConfigError("fusion", config.get("fusion"), "null unless an sfs stage is set")
        cloud = clock.call("fusion", stages["fusion"].fuse, depth, itof, grid)
    if "surface" in stages:
        if cloud is None:
            raise ConfigError("surface", config.get("surface"), "null unless a fusion stage is set")
        mesh = clock.call("surface", stages["surface"].reconstruct, cloud)
    return Products(truth, acq, image, upscaled, depth, itof, cloud, mesh)
