"""Hydra looks for sweeper and launcher classes in the ``hydra_plugins`` namespace; these are
nirspi-pipe's.

The implementations live in :mod:`nirspi_pipe.app.sweeper` and :mod:`nirspi_pipe.app.launcher`.
"""

from nirspi_pipe.app.launcher import NirspiLauncherBase
from nirspi_pipe.app.study import StudySweeperBase, register_config
from nirspi_pipe.app.sweeper import NirspiSweeperBase


class NirspiSweeper(NirspiSweeperBase):
    """Config-hash keyed, resumable grid sweeper with progress (``hydra/sweeper=nirspi``)."""


class NirspiOptunaSweeper(StudySweeperBase):
    """An Optuna study in a database over keyed job folders (``hydra/sweeper=optuna``)."""


class NirspiLauncher(NirspiLauncherBase):
    """Sweep jobs as forked children of the sweeping process (``hydra/launcher=nirspi``)."""


register_config()  # hydra/sweeper=optuna: nirspi_pipe.app.study's sweeper over the plugin's

__all__ = ["NirspiLauncher", "NirspiOptunaSweeper", "NirspiSweeper"]
