"""Hydra looks for sweeper and launcher classes in the ``hydra_plugins`` namespace; these are
nirspi-pipe's.

The implementations live in :mod:`nirspi_pipe.sweeper` and :mod:`nirspi_pipe.launcher`.
"""

from nirspi_pipe.launcher import NirspiLauncherBase
from nirspi_pipe.sweeper import NirspiSweeperBase


class NirspiSweeper(NirspiSweeperBase):
    """Config-hash keyed, resumable grid sweeper with progress (``hydra/sweeper=nirspi``)."""


class NirspiLauncher(NirspiLauncherBase):
    """Sweep jobs as forked children of the sweeping process (``hydra/launcher=nirspi``)."""


__all__ = ["NirspiLauncher", "NirspiSweeper"]
