"""What Hydra's own node may build: the app's targets, checked by the app (issue 42).

The runner's allow-list (:mod:`nirspi_pipe.targets`) holds the stage classes a job builds and
refuses every class of Hydra, OmegaConf and the app. Hydra's node (``hydra.*``) names classes
that Hydra builds, never the runner:

* the app's results callback (:data:`APP_TARGETS`), at ``hydra.callbacks.<name>._target_``;
* a launcher or sweeper plugin (:data:`HYDRA_PLUGIN_PREFIXES`), at ``hydra.launcher._target_`` and
  ``hydra.sweeper._target_`` only: Hydra accepts only classes registered as Hydra plugins there;
* a logging handler (:data:`LOGGING_CLASSES`), at the ``class``/``()`` key of a handler of
  ``hydra.job_logging``/``hydra.hydra_logging`` (Python's ``logging.config`` builds it);
* an Optuna sampler or pruner, at ``hydra.sweeper.sampler._target_``/``hydra.sweeper.pruner._target_``
  (:data:`nirspi_pipe.app.allowlist.OPTUNA_TARGET_PREFIXES`; :mod:`nirspi_pipe.app.entry` also
  requires the Optuna sweeper).

:func:`check_target` allows these at their keys and hands everything else to the runner's
:func:`nirspi_pipe.targets.check_target`. The app's checks (the invocation, each job's node, swept
values) call these functions; the runner never imports this module (tests/test_architecture.py).
"""

from __future__ import annotations

import re
from typing import Any

from nirspi_pipe import targets
from nirspi_pipe.app.allowlist import OPTUNA_TARGET_PREFIXES

__all__ = ["APP_TARGETS", "HYDRA_PLUGIN_PREFIXES", "LOGGING_CLASSES", "check_target", "check_targets"]

#: The app's classes that Hydra builds from its node: the multirun results callback
#: (``hydra.callbacks.collect`` in conf/config.yaml).
APP_TARGETS: frozenset[str] = frozenset({"nirspi_pipe.app.results.CollectResults"})
_CALLBACK_KEY = re.compile(r"^hydra\.callbacks\.[^.]+\._target_$")

#: Where Hydra's own plugin classes live. Only ``hydra.launcher._target_`` and
#: ``hydra.sweeper._target_`` may name one: Hydra builds those itself and accepts only classes
#: registered as Hydra plugins (in these packages); their nested nodes are checked like any other.
HYDRA_PLUGIN_PREFIXES = ("hydra_plugins.", "hydra._internal.core_plugins.")
_HYDRA_PLUGIN_KEYS = ("hydra.launcher._target_", "hydra.sweeper._target_")

#: The handler classes of Hydra's default logging configs (``hydra/job_logging/default.yaml``):
#: the only classes a ``class``/``()`` key of a logging node may name.
LOGGING_CLASSES = frozenset({"logging.StreamHandler", "logging.FileHandler", "logging.NullHandler"})
#: Keys where Python's ``logging.config`` builds a handler: a ``class``/``()`` there may name one of
#: :data:`LOGGING_CLASSES` (nowhere else: a key path merely containing "logging" unlocks nothing).
_LOGGING_CLASS_KEY = re.compile(r"^hydra\.(job|hydra)_logging\.handlers\.[^.]+\.(class|\(\))$")


def _hydra_builds(target: str, key: str) -> bool:
    """True when Hydra (not the runner) builds ``target`` at ``key`` and the app allows it there."""
    if target in APP_TARGETS and _CALLBACK_KEY.match(key):
        return True
    if key in _HYDRA_PLUGIN_KEYS and target.startswith(HYDRA_PLUGIN_PREFIXES):
        return True  # Hydra accepts only its registered plugin classes here (hydra.core.plugins)
    if _LOGGING_CLASS_KEY.match(key) and target in LOGGING_CLASSES:
        return True
    prefix = OPTUNA_TARGET_PREFIXES.get(key.removeprefix("hydra."))
    return prefix is not None and target.startswith(prefix) and target[len(prefix) :].isidentifier()


def check_target(target: Any, key: str) -> None:
    """:func:`nirspi_pipe.targets.check_target`, and the classes Hydra builds from its own node,
    each at its keys (module docstring). A one-line :class:`~nirspi_pipe.errors.ConfigError`
    naming ``key`` otherwise; only strings are compared, nothing is imported."""
    if isinstance(target, str) and key.startswith("hydra.") and _hydra_builds(target, key):
        return
    targets.check_target(target, key)


def check_targets(node: Any, path: str = "") -> None:
    """:func:`check_target` on every target of a plain config tree
    (:func:`nirspi_pipe.targets.find_targets`), Hydra's node included, before any is built."""
    for key, value in targets.find_targets(node, path):
        check_target(value, key)
