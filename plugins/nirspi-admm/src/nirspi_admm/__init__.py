"""nirspi-admm: an example nirspi-pipe plugin adding ``solver=admm_tv``.

nirspi-pipe finds it through the entry point ``admm = "nirspi_admm:register"`` in the group
``nirspi_pipe.plugins`` and adds the config folder :func:`register` returns to Hydra's search
path, so ``nirspi-run solver=admm_tv`` works once the package is installed.
"""

from __future__ import annotations

from nirspi_admm.solver import ADMMTVSolver, admm_tv

__all__ = ["ADMMTVSolver", "admm_tv", "register"]


def register() -> str:
    """Entry point for nirspi-pipe: the config folder holding ``solver/admm_tv.yaml``, after
    registering its schema (the defaults of :class:`ADMMTVSolver`, the one place they live)."""
    from nirspi_pipe.app.configs import register_schemas

    register_schemas("nirspi_admm.conf")
    return "pkg://nirspi_admm.conf"
