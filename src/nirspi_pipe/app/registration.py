"""Hydra's registry of plugin classes: nirspi-pipe's sweeper and launcher.

A module of its own, above :mod:`nirspi_pipe.app.sweeper` and :mod:`nirspi_pipe.app.launcher`:
the classes Hydra instantiates live in the ``hydra_plugins`` namespace, which imports both.
"""

from __future__ import annotations

__all__ = ["register_hydra_plugins"]


def register_hydra_plugins() -> None:
    """Register nirspi-pipe's Hydra plugin classes explicitly.

    Hydra only instantiates sweepers and launchers from the ``hydra_plugins`` namespace, which it
    discovers by scanning; that scan misses editable installs (Hydra issue #2359). Registering the
    classes by hand makes ``hydra/sweeper=nirspi`` and ``hydra/launcher=nirspi`` work for every
    kind of install.
    """
    from hydra.core.plugins import Plugins  # start-up: loads hydra, omegaconf (116 ms here)

    from nirspi_pipe.app.plugins import trusted_import_path  # start-up: loads hydra, omegaconf (180 ms here)

    with trusted_import_path():  # never a hydra_plugins module of the working directory
        # trusted path: imported only inside trusted_import_path(), so never from the working directory
        from hydra_plugins.nirspi_pipe_sweeper import NirspiLauncher, NirspiOptunaSweeper, NirspiSweeper

    Plugins.instance().register(NirspiSweeper)
    Plugins.instance().register(NirspiOptunaSweeper)
    Plugins.instance().register(NirspiLauncher)
