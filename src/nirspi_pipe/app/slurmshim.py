"""The ``sacct`` shim for a SLURM cluster without accounting, used by the ``nirspi`` sweeper
(:mod:`nirspi_pipe.app.sweeper`) with a SLURM launcher: one line said, submitit's repeated
warnings dropped, ``sacct``'s stderr silenced.
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["quiet_sacct_without_accounting"]


class _DropSacctNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "Bypassing sacct error" not in record.getMessage()


def quiet_sacct_without_accounting() -> bool:
    """On a SLURM cluster without accounting, ``sacct`` fails on every poll and submitit warns
    each time ("Bypassing sacct error", plus sacct's own "accounting storage is disabled" on
    stderr). Detect that once, say it in one line, drop those warnings and run ``sacct`` through a
    shim that silences its stderr (first on ``PATH`` of the sweeping process only). Job states
    then come from submitit's result files, which is all the sweep needs. True when quieted.
    The shim's temporary folder is removed when the process exits."""
    sacct = shutil.which("sacct")
    if sacct is None:
        return False
    try:
        probe = subprocess.run(
            [sacct, "-n", "-X", "-j", "1", "-o", "JobID"],
            check=False,
            capture_output=True,
            text=True,
            timeout=20,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.SubprocessError):
        return False
    if "accounting storage is disabled" not in (probe.stderr or "").lower():
        return False
    shim_dir = Path(tempfile.mkdtemp(prefix="nirspi-sacct-"))
    atexit.register(shutil.rmtree, shim_dir, ignore_errors=True)  # the shim lives as long as the sweep
    shim = shim_dir / "sacct"
    shim.write_text(f'#!/bin/sh\nexec "{sacct}" "$@" 2>/dev/null\n')
    shim.chmod(0o755)
    os.environ["PATH"] = f"{shim_dir}{os.pathsep}{os.environ.get('PATH', '')}"
    logging.getLogger("submitit").addFilter(_DropSacctNoise())
    print(
        "nirspi-run: this SLURM cluster keeps no accounting (sacct): job states come from the result files", flush=True
    )
    return True
