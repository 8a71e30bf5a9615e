"""Hydra looks for sweeper classes in the ``hydra_plugins`` namespace; this is nirspi-pipe's.

The implementation lives in :mod:`nirspi_pipe.sweeper`.
"""

from nirspi_pipe.sweeper import NirspiSweeperBase


class NirspiSweeper(NirspiSweeperBase):
    """Config-hash keyed, resumable grid sweeper with progress (``hydra/sweeper=nirspi``)."""


__all__ = ["NirspiSweeper"]
