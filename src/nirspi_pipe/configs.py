"""The config catalogue, through Hydra's public API only: which groups and options exist, and
composing a config (the runner's side; no stage imports this module).

Group and option listings go through ``hydra.initialize_config_module`` and the public
:class:`hydra.core.config_loader.ConfigLoader` interface of ``GlobalHydra``; when a Hydra app is
already running (``nirspi-run``) its own global instance is used. The experiments folder and
installed plugins' config folders are on the search path (:func:`nirspi_pipe.plugins.activate`
registers a public ``SearchPathPlugin``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from typing import Any

import numpy as np

__all__ = [
    "CONFIG_MODULE", "CONFIG_NAME", "group_options", "config_groups", "all_groups", "scan_indices", "render_scene",
]

#: The package holding the primary config and its groups.
CONFIG_MODULE = "nirspi_pipe.conf"
#: The primary config's name.
CONFIG_NAME = "config"


@contextmanager
def _loader() -> Iterator[Any]:
    """Hydra's public config loader, initialising Hydra on our config module when no app runs."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from nirspi_pipe.plugins import activate

    activate()  # plugin config folders join the search path
    gh = GlobalHydra.instance()
    if gh.is_initialized():
        yield gh.config_loader()
        return
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        yield GlobalHydra.instance().config_loader()


@lru_cache(maxsize=1)
def _catalogue() -> dict[str, tuple[str, ...]]:
    """``{group: options}`` of every config group (nested ones as ``parent/child``), read once."""
    from hydra.core.object_type import ObjectType

    found: dict[str, tuple[str, ...]] = {}
    with _loader() as loader:

        def walk(parent: str) -> None:
            for g in loader.get_group_options(parent, ObjectType.GROUP):
                path = f"{parent}/{g}" if parent else g
                if path == "hydra":
                    continue
                found[path] = tuple(sorted(loader.get_group_options(path, ObjectType.CONFIG)))
                walk(path)

        walk("")
    return found


def group_options(group: str) -> list[str]:
    """Options of a config group (``scan`` → ``["basic", …]``), plugins included."""
    return list(_catalogue().get(group, ()))


def config_groups(parent: str = "") -> list[str]:
    """Config groups directly under ``parent`` (top level by default), Hydra's own excluded."""
    prefix = f"{parent}/" if parent else ""
    return sorted(g[len(prefix):] for g in _catalogue() if g.startswith(prefix) and "/" not in g[len(prefix):])


def all_groups() -> frozenset[str]:
    """Every config group, nested ones as ``parent/child``, Hydra's own excluded."""
    return frozenset(_catalogue())


def scan_indices(order: str, ratio: float, n: int) -> np.ndarray:
    """Indices of the scan option ``order`` (``conf/scan/<order>.yaml``, plugins included) at
    ``ratio`` for ``n × n`` patterns: what a recording that names its order was measured with.
    Raises :class:`~nirspi_pipe.device.recording.RecordingError` naming ``order`` when it is not
    an option. Handed to the recorded source by the runner."""
    from hydra import compose
    from hydra.utils import instantiate

    from nirspi_pipe.device.recording import RecordingError

    allowed = group_options("scan")
    if order not in allowed:
        raise RecordingError("order", f"{order!r} is not a scan option; allowed: {', '.join(allowed)}")
    with _loader():
        cfg = compose(CONFIG_NAME, overrides=[f"scan={order}", f"scan.ratio={float(ratio)!r}"])
    return np.asarray(instantiate(cfg.scan).select(n), dtype=np.int64)


def render_scene(scene: str, resolution: int, overrides: list[str] | None = None) -> np.ndarray:
    """Relative radiance ``(n, n)`` of the ``scene=<scene>`` option at ``resolution`` (for the
    device emulator's command line)."""
    from hydra import compose
    from hydra.utils import instantiate

    with _loader():
        cfg = compose(CONFIG_NAME, overrides=[f"scene={scene}", f"camera.resolution={resolution}", *(overrides or [])])
    camera = instantiate(cfg.camera)
    return instantiate(cfg.scene).render(camera).radiance
