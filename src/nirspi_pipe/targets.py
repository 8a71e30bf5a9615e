"""What a config may build: the allow-list of ``_target_`` classes (docs/hostile.md, issue 24).

A config node ``{_target_: a.b.C, x: 1}`` becomes ``a.b.C(x=1)``. Were any dotted name accepted,
a config value could call ``os.system`` or import a module from the working directory. So a
target is built only when it is on the allow-list, and the check is a comparison of strings made
**before** anything is imported or called:

* :data:`PROJECT_TARGETS`: nirspi-pipe's own stage classes (every ``_target_`` the shipped config
  options and experiments name, and the nested classes whose defaults the schemas expand);
* the classes that installed plugins register, read from the installed distributions' metadata
  (entry-point group ``nirspi_pipe.targets``, see docs/plugins.md) without importing them::

      [project.entry-points."nirspi_pipe.targets"]
      ADMMTVSolver = "nirspi_admm:ADMMTVSolver"     # allows _target_: nirspi_admm.ADMMTVSolver

A target in a layer above the runner (Hydra, OmegaConf, the app, the config groups, the
command-line tools: :data:`UPPER_LAYERS`) is refused, whatever the lists hold (a plugin
cannot register one): the runner builds stages without the config layer (issue 42, checked at run
time by tests/test_layering_runtime.py). Anything else is a one-line
:class:`~nirspi_pipe.errors.ConfigError` naming the key. The runner
(:func:`nirspi_pipe.pipeline.build`) checks every node it builds. The classes Hydra itself builds
from its own node (the results callback, launcher and sweeper plugins, logging handlers) are the
app's business: it allows them at their keys of ``hydra.*`` and hands every other key to
:func:`check_target` (:mod:`nirspi_pipe.app.hydratargets`). This module imports neither Hydra nor
OmegaConf, and names no class of the app.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Iterator
from functools import lru_cache
from importlib import metadata
from typing import Any

from nirspi_pipe.errors import ConfigError

__all__ = [
    "PROJECT_TARGETS",
    "TARGET_ENTRY_POINTS",
    "UPPER_LAYERS",
    "above_the_runner",
    "plugin_targets",
    "allowed_targets",
    "find_targets",
    "check_target",
    "check_once",
    "check_targets",
    "resolve",
    "locate",
]

#: Entry-point group in which plugins register the classes their configs may build.
TARGET_ENTRY_POINTS = "nirspi_pipe.targets"

#: nirspi-pipe's own classes that a config may build. ``tests/test_security.py`` checks that
#: every ``_target_`` of every shipped option and experiment is here, and that each one imports.
PROJECT_TARGETS: frozenset[str] = frozenset(
    {
        "nirspi_pipe.types.Camera",
        # scene
        "nirspi_pipe.scene.objects.Sphere",
        "nirspi_pipe.scene.objects.ImageTarget",
        "nirspi_pipe.scene.shapes.Cube",
        "nirspi_pipe.scene.shapes.MeshScene",
        "nirspi_pipe.scene.shapes.Plane",
        "nirspi_pipe.scene.shapes.Torus",
        "nirspi_pipe.scene.shapes.UShape",
        "nirspi_pipe.scene.testshapes.GeneratedShape",
        # source and its effects
        "nirspi_pipe.sources.simulator.Simulator",
        "nirspi_pipe.sources.recorded.Recorded",
        "nirspi_pipe.sources.stream.Stream",
        "nirspi_pipe.physics.effects.forward_model",
        "nirspi_pipe.physics.fog.NoFog",
        "nirspi_pipe.physics.fog.MieFog",
        "nirspi_pipe.physics.fog.MeasuredFog",
        "nirspi_pipe.physics.light.Background",
        "nirspi_pipe.physics.detector.IdealDetector",
        "nirspi_pipe.physics.detector.Photodiode",
        "nirspi_pipe.physics.budget.PhotonBudget",
        # scan orders
        "nirspi_pipe.patterns.orders.Basic",
        "nirspi_pipe.patterns.orders.CakeCutting",
        "nirspi_pipe.patterns.orders.Hilbert",
        "nirspi_pipe.patterns.orders.Random",
        "nirspi_pipe.patterns.orders.RussianDoll",
        "nirspi_pipe.patterns.orders.Sequency",
        "nirspi_pipe.patterns.orders.Spiral",
        "nirspi_pipe.patterns.orders.Variance",
        "nirspi_pipe.patterns.orders.Zigzag",
        # solvers
        "nirspi_pipe.solvers.completion.CompletionSolver",
        "nirspi_pipe.solvers.correlation.CorrelationSolver",
        "nirspi_pipe.solvers.fista_tv.FistaTVSolver",
        "nirspi_pipe.solvers.fwht.FWHTSolver",
        "nirspi_pipe.solvers.lstsq.LstsqSolver",
        "nirspi_pipe.solvers.omp.OMPSolver",
        # upscalers
        "nirspi_pipe.upscale.Bicubic",
        "nirspi_pipe.upscale.FSRCNN",
        # 3D
        "nirspi_pipe.sfs.models.LaxFriedrichsSFS",
        "nirspi_pipe.sfs.models.OrenNayarSFS",
        "nirspi_pipe.sfs.models.PerspectiveSFS",
        "nirspi_pipe.sfs.models.PhongSFS",
        "nirspi_pipe.sfs.oracle.TruthDepth",
        "nirspi_pipe.itof.cw4.ContinuousWave4",
        "nirspi_pipe.mesh.fusion.ItofFusion",
        "nirspi_pipe.mesh.powercrust.PowerCrust",
        "nirspi_pipe.mesh.poisson.ScreenedPoisson",
        "nirspi_pipe.mesh.viewmesh.ViewTriangulation",
        # metrics
        "nirspi_pipe.metrics.ImageMetrics",
        "nirspi_pipe.upscale.metrics.UpscaleMetrics",
        "nirspi_pipe.mesh.metrics3d.Metrics3D",
    }
)

#: The layers above the runner, by dotted prefix: Hydra and its plugin namespace, OmegaConf, the
#: app, the config groups (``nirspi_pipe.conf`` registers the app's schemas on import) and the
#: command-line tools that compose configs (the same split as tests/test_architecture.py, which
#: checks that this list covers its own). A ``_target_`` in one of them is never built by the
#: runner. ``nirspi_pipe.<name>`` alone is the package's facade, whose names the app serves lazily.
UPPER_LAYERS: tuple[str, ...] = (
    "hydra",
    "hydra_plugins",
    "omegaconf",
    "nirspi_pipe.app",
    "nirspi_pipe.conf",
    "nirspi_pipe.experiments",
    "nirspi_pipe.benchmarks",
    "nirspi_pipe.bench",
    "nirspi_pipe.readme_numbers",
    "nirspi_pipe.hardcases",
    "nirspi_pipe.reproduce",
)


def above_the_runner(target: str) -> bool:
    """True when the dotted name ``target`` lies in :data:`UPPER_LAYERS` or is an attribute of the
    package's facade (``nirspi_pipe.run``): a string comparison, nothing is imported."""
    name = target.strip()
    parts = name.split(".")
    if parts[0] == "nirspi_pipe" and len(parts) <= 2:
        return True
    return any(name == layer or name.startswith(layer + ".") for layer in UPPER_LAYERS)


def trusted_paths() -> list[str]:
    """The ``sys.path`` entries plugins may come from: absolute ones other than the working
    directory (``''``, ``.``, relative entries and the working directory itself are left out,
    so a ``*.dist-info`` or ``hydra_plugins`` folder next to a notebook is never used)."""
    cwd = os.path.realpath(os.getcwd())
    return [p for p in sys.path if p and os.path.isabs(p) and os.path.realpath(p) != cwd]


def _location(ep: metadata.EntryPoint) -> str:
    """The folder of ``ep``'s distribution; ``""`` when there is none or it cannot say."""
    dist = getattr(ep, "dist", None)
    if dist is None:
        return ""
    try:
        return os.path.realpath(str(dist.locate_file("")))
    except Exception:  # noqa: BLE001 - a distribution that cannot say where it is: not trusted
        return ""


def installed(ep: metadata.EntryPoint) -> bool:
    """True when ``ep`` belongs to a distribution found on a :func:`trusted_paths` entry. An
    entry point without a distribution (made in code, not installed) is refused: plugins come
    only from installed distributions (tests/test_plugins.py)."""
    where = _location(ep)
    return bool(where) and where in {os.path.realpath(p) for p in trusted_paths()}


def origin(ep: metadata.EntryPoint) -> str:
    """Where an entry point's distribution lies (for messages): its folder, or what it lacks."""
    if getattr(ep, "dist", None) is None:
        return "no distribution (made in code)"
    return _location(ep) or "a distribution that cannot say where it is"


def _target_name(ep: metadata.EntryPoint) -> str:
    """The dotted name a ``nirspi_pipe.targets`` entry point registers (``module:Attr`` → ``module.Attr``)."""
    module, _, attr = ep.value.partition(":")
    return f"{module.strip()}.{attr.strip()}" if attr.strip() else module.strip()


def untrusted(group: str) -> dict[str, str]:
    """``{name: origin}`` of the entry points of ``group`` that :func:`installed` refuses (for
    ``nirspi_pipe.targets`` the name is the dotted target). They are never used; errors and the
    plugin report name them, so that a plugin outside the installed distributions is not ignored
    without a word."""
    out: dict[str, str] = {}
    for ep in metadata.entry_points(group=group):
        if installed(ep):
            continue
        out.setdefault(_target_name(ep) if group == TARGET_ENTRY_POINTS else ep.name, origin(ep))
    return out


@lru_cache(maxsize=1)
def plugin_targets() -> frozenset[str]:
    """Dotted names that installed plugins register (entry-point group ``nirspi_pipe.targets``:
    ``Name = "module:Attr"`` allows ``module.Attr``). Read from the installed distributions'
    metadata (:func:`installed`: never from the working directory): nothing is imported. Read once per process (installing a plugin needs a new process)."""
    found = set()
    for ep in metadata.entry_points(group=TARGET_ENTRY_POINTS):
        if not installed(ep):
            continue
        name = _target_name(ep)
        if all(part.isidentifier() for part in name.split(".")):
            found.add(name)
    return frozenset(found)


@lru_cache(maxsize=4)
def _allowed(project: frozenset[str], plugins: frozenset[str]) -> frozenset[str]:
    return frozenset(t for t in project | plugins if not above_the_runner(t))


def allowed_targets() -> frozenset[str]:
    """Every ``_target_`` a config may name: :data:`PROJECT_TARGETS` and :func:`plugin_targets`,
    less any name :func:`above_the_runner` (which no list can allow)."""
    return _allowed(PROJECT_TARGETS, plugin_targets())


def find_targets(node: Any, path: str) -> Iterator[tuple[str, Any]]:
    """``(key, value)`` of every place in a plain config tree (dicts and lists) that names
    something to build: ``_target_`` keys, and ``()``/``class`` keys below a key naming
    "logging" (the factories of Python's ``logging.config``, which Hydra applies to its
    ``job_logging`` node; the app allows its handler classes, :mod:`nirspi_pipe.app.hydratargets`)."""
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{path}.{k}" if path else str(k)
            if k == "_target_" or (k in ("()", "class") and "logging" in key):
                yield key, v
            else:
                yield from find_targets(v, key)
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            yield from find_targets(v, f"{path}.{i}" if path else str(i))


def _allowed_text() -> str:
    plugins = sorted(plugin_targets())
    extra = f"; plugins register theirs: {', '.join(plugins)}" if plugins else ""
    return (
        "one of nirspi-pipe's stage classes (the _target_ of a shipped option, e.g. "
        f"nirspi_pipe.solvers.fwht.FWHTSolver){extra}; a plugin registers a class in the entry-point "
        f"group {TARGET_ENTRY_POINTS} (docs/plugins.md)"
    )


def check_target(target: Any, key: str) -> None:
    """Raise a one-line :class:`ConfigError` naming ``key`` unless ``target`` is allowed. Only
    strings are compared: nothing is imported. A target :func:`above_the_runner` is refused,
    saying why, even when an allow-list holds it (:func:`allowed_targets` leaves those out)."""
    if isinstance(target, str) and target in allowed_targets():
        return
    if isinstance(target, str) and above_the_runner(target):
        raise ConfigError(
            key,
            target,
            "a stage class of the runner (e.g. nirspi_pipe.solvers.fwht.FWHTSolver), never a class of a "
            f"layer above it ({', '.join(p + '.*' for p in UPPER_LAYERS)}, or the facade nirspi_pipe.<name>): "
            "the runner builds stages without Hydra, OmegaConf or the app",
            absolute=True,
        )
    allowed = _allowed_text()
    where = untrusted(TARGET_ENTRY_POINTS).get(target) if isinstance(target, str) else None
    if where:  # registered, but not by an installed distribution (a *.dist-info in the working directory)
        allowed += (
            f"; {target} is registered by an entry point outside the installed distributions ({where}), "
            "which is never used: plugins come only from installed distributions (pip install the plugin)"
        )
    raise ConfigError(key, target, allowed, absolute=True)


#: The target strings that passed :func:`check_target` in this process and the allow-list they
#: passed against (the :func:`allowed_targets` object, held so it is not collected): :func:`check_once`.
_PASSED: list[tuple[frozenset[str], set[str]]] = []


def check_once(target: Any, key: str) -> None:
    """:func:`check_target`, once per target string and allow-list in this process (issue 42:
    each ``_target_`` checked once). A string that passed against the current
    :func:`allowed_targets` object is not compared again, wherever it appears: the app's schema
    catalogue checks an option's target when Hydra first composes the option
    (:func:`nirspi_pipe.app.configs.schema_defaults`, through :func:`resolve`), and the job's
    plan then names the same string (:class:`nirspi_pipe.instantiate.Plan`). Nothing is weakened:
    the verdict of :func:`check_target` depends only on the string and the allow-list, a string
    is recorded only after it passed, the record is dropped when the allow-list is another object
    (a plugin list read again, ``PROJECT_TARGETS`` replaced), and a refusal is never recorded, so
    every refusal is :func:`check_target`'s own one line naming the key where it was found."""
    allowed = allowed_targets()
    if not _PASSED or _PASSED[0][0] is not allowed:
        _PASSED[:] = [(allowed, set())]
    passed = _PASSED[0][1]
    if isinstance(target, str) and target in passed:
        return
    check_target(target, key)
    if isinstance(target, str):
        passed.add(target)


def check_targets(node: Any, path: str = "") -> None:
    """Check every target in a plain config tree (:func:`find_targets`) before any is built."""
    for key, value in find_targets(node, path):
        check_target(value, key)


def locate(target: str) -> Any:
    """The object a dotted path (``package.module.Name``) names, or None. Imports: call it only
    on a name that :func:`check_target` accepted (:func:`resolve` does both)."""
    parts = target.split(".")
    for i in range(len(parts) - 1, 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return obj
    return None


def resolve(target: Any, key: str) -> Any:
    """The class an allowed ``_target_`` names (checked first, then imported), or None when an
    allowed name does not import (a plugin registered but not installed). Each string is
    checked once per process and allow-list (:func:`check_once`)."""
    check_once(target, key)
    return locate(str(target))
