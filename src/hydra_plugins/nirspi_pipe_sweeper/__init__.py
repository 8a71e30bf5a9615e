"""Hydra looks for sweeper and launcher classes in the ``hydra_plugins`` namespace; these are
nirspi-pipe's.

The implementations live in :mod:`nirspi_pipe.app.sweeper` and :mod:`nirspi_pipe.app.launcher`.
"""

from nirspi_pipe.app.launcher import NirspiLauncherBase
from nirspi_pipe.app.sweeper import NirspiSweeperBase


class NirspiSweeper(NirspiSweeperBase):
    """Config-hash keyed, resumable grid sweeper with progress (``hydra/sweeper=nirspi``)."""


class NirspiLauncher(NirspiLauncherBase):
    """Sweep jobs as forked children of the sweeping process (``hydra/launcher=nirspi``)."""


__all__ = ["NirspiLauncher", "NirspiSweeper"]
