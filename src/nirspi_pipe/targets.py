"""What a config may build: the allow-list of ``_target_`` classes (docs/hostile.md, issue 24).

A config node ``{_target_: a.b.C, x: 1}`` becomes ``a.b.C(x=1)``. Were any dotted name accepted,
a config value could call ``os.system`` or import a module from the working directory. So a
target is built only when it is on the allow-list, and the check is a comparison of strings made
**before** anything is imported or called:

* :data:`PROJECT_TARGETS`: nirspi-pipe's own stage classes (every ``_target_`` the shipped config
  options and experiments name, and the nested classes whose defaults the schemas expand), and
  its one Hydra callback (:class:`nirspi_pipe.app.results.CollectResults`);
* the classes that installed plugins register, read from the installed distributions' metadata
  (entry-point group ``nirspi_pipe.targets``, see docs/plugins.md) without importing them::

      [project.entry-points."nirspi_pipe.targets"]
      ADMMTVSolver = "nirspi_admm:ADMMTVSolver"     # allows _target_: nirspi_admm.ADMMTVSolver

Anything else is a one-line :class:`~nirspi_pipe.errors.ConfigError` naming the key. The
runner (:func:`nirspi_pipe.pipeline.build`) checks every node it builds; ``nirspi-run`` and
``nirspi_pipe.run`` also check the whole composed config, Hydra's own node included, before
Hydra builds its callbacks, launcher and sweeper (:func:`nirspi_pipe.app.validate.check_config`).
This module imports neither Hydra nor OmegaConf.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Iterator
from functools import lru_cache
from importlib import metadata
from typing import Any

from nirspi_pipe.errors import ConfigError

__all__ = [
    "PROJECT_TARGETS",
    "TARGET_ENTRY_POINTS",
    "HYDRA_PLUGIN_PREFIXES",
    "LOGGING_CLASSES",
    "plugin_targets",
    "allowed_targets",
    "find_targets",
    "check_target",
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
        # metrics
        "nirspi_pipe.metrics.ImageMetrics",
        "nirspi_pipe.upscale.metrics.UpscaleMetrics",
        "nirspi_pipe.mesh.metrics3d.Metrics3D",
        # Hydra callback (hydra.callbacks.collect)
        "nirspi_pipe.app.results.CollectResults",
    }
)

#: Where Hydra's own plugin classes live. Only ``hydra.launcher._target_`` and
#: ``hydra.sweeper._target_`` may name one: Hydra builds those itself and accepts only classes
#: registered as Hydra plugins (in these packages); their nested nodes are checked like any other.
HYDRA_PLUGIN_PREFIXES = ("hydra_plugins.", "hydra._internal.core_plugins.")
_HYDRA_PLUGIN_KEYS = ("hydra.launcher._target_", "hydra.sweeper._target_")

#: The handler classes of Hydra's default logging configs (``hydra/job_logging/default.yaml``):
#: the only classes a ``class``/``()`` key of a logging node may name.
LOGGING_CLASSES = frozenset({"logging.StreamHandler", "logging.FileHandler", "logging.NullHandler"})


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


def allowed_targets() -> frozenset[str]:
    """Every ``_target_`` a config may name: :data:`PROJECT_TARGETS` and :func:`plugin_targets`."""
    return PROJECT_TARGETS | plugin_targets()


#: Keys where Python's ``logging.config`` builds a handler: a ``class``/``()`` there may name one of
#: :data:`LOGGING_CLASSES` (nowhere else: a key path merely containing "logging" unlocks nothing).
_LOGGING_CLASS_KEY = re.compile(r"^hydra\.(job|hydra)_logging\.handlers\.[^.]+\.(class|\(\))$")
#: Optuna's samplers and pruners (hydra-optuna-sweeper, issue 34): only at these two keys, and
#: only from these packages; :mod:`nirspi_pipe.app.entry` also requires the Optuna sweeper.
OPTUNA_TARGET_KEYS = {
    "hydra.sweeper.sampler._target_": "optuna.samplers.",
    "hydra.sweeper.pruner._target_": "optuna.pruners.",
}


def _in_logging(key: str) -> bool:
    return key.startswith(("hydra.job_logging.", "hydra.hydra_logging.")) or "logging" in key


def find_targets(node: Any, path: str) -> Iterator[tuple[str, Any]]:
    """``(key, value)`` of every place in a plain config tree (dicts and lists) that names
    something to build: ``_target_`` keys, and ``()``/``class`` keys of logging factories
    (Python's ``logging.config``, which Hydra applies to ``hydra.job_logging``)."""
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{path}.{k}" if path else str(k)
            if k == "_target_" or (k in ("()", "class") and _in_logging(key)):
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
    strings are compared: nothing is imported."""
    if isinstance(target, str) and target in allowed_targets():
        return
    if isinstance(target, str) and key in _HYDRA_PLUGIN_KEYS and target.startswith(HYDRA_PLUGIN_PREFIXES):
        return  # Hydra accepts only its registered plugin classes here (hydra.core.plugins)
    if isinstance(target, str) and _LOGGING_CLASS_KEY.match(key) and target in LOGGING_CLASSES:
        return
    prefix = OPTUNA_TARGET_KEYS.get(key)
    if isinstance(target, str) and prefix and target.startswith(prefix) and target[len(prefix) :].isidentifier():
        return
    allowed = _allowed_text()
    where = untrusted(TARGET_ENTRY_POINTS).get(target) if isinstance(target, str) else None
    if where:  # registered, but not by an installed distribution (a *.dist-info in the working directory)
        allowed += (
            f"; {target} is registered by an entry point outside the installed distributions ({where}), "
            "which is never used: plugins come only from installed distributions (pip install the plugin)"
        )
    raise ConfigError(key, target, allowed, absolute=True)


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
    allowed name does not import (a plugin registered but not installed)."""
    check_target(target, key)
    return locate(str(target))
