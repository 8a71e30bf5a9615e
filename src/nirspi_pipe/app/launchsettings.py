"""The nirspi launcher's settings and their checks, in a module of their own: the launcher uses
them, and so does the entry check (:func:`nirspi_pipe.app.validate.check_sweep_settings`) before a
sweep starts (importing the launcher there would close an import circle through the CLI)."""

from __future__ import annotations

from typing import Any

from nirspi_pipe.errors import ConfigError

__all__ = ["DEFAULT_TIMEOUT_S", "check_launcher_settings"]

#: Default deadline of one job, ``hydra.launcher.timeout_s``: 30 minutes, issue 24's suggestion of a
#: generous default; half the SLURM launcher's per-job ``timeout_min: 60`` (conf/hydra/launcher/slurm.yaml).
DEFAULT_TIMEOUT_S = 1800.0


def check_launcher_settings(n_jobs: Any, timeout_s: Any) -> None:
    """Raise a one-line :class:`ConfigError` naming ``hydra.launcher.n_jobs`` or
    ``hydra.launcher.timeout_s`` when it is out of range."""
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, int) or not (n_jobs == -1 or n_jobs >= 1):
        raise ConfigError("hydra.launcher.n_jobs", n_jobs, "-1 (one per core) or an integer >= 1", absolute=True)
    if timeout_s is not None and (
        isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not (0 < timeout_s < float("inf"))
    ):
        raise ConfigError(
            "hydra.launcher.timeout_s", timeout_s, "a number of seconds > 0, or null (no deadline)", absolute=True
        )
