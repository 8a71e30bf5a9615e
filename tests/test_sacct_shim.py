"""The sacct shim of a SLURM cluster without accounting (``app.slurmshim.quiet_sacct_without_accounting``):
first on ``PATH`` while the sweep runs, its temporary folder gone when the process exits."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

PROBE = """
import os
from nirspi_pipe.app.slurmshim import quiet_sacct_without_accounting
quieted = quiet_sacct_without_accounting()
first = os.environ["PATH"].split(os.pathsep)[0]
print(quieted, first, os.path.isfile(os.path.join(first, "sacct")))
"""


@pytest.mark.skipif(sys.platform == "win32", reason="a POSIX shell script stands in for sacct")
@pytest.mark.parametrize("accounting", [False, True])
def test_shim_only_without_accounting_and_removed_at_exit(tmp_path: Path, accounting: bool) -> None:
    fake = tmp_path / "bin" / "sacct"
    fake.parent.mkdir()
    message = "" if accounting else "sacct: error: Slurm accounting storage is disabled"
    fake.write_text(f"#!/bin/sh\necho '{message}' >&2\nexit {0 if accounting else 1}\n")
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120, check=True
    ).stdout.split()
    quieted, first, has_shim = out[-3] == "True", Path(out[-2]), out[-1] == "True"
    if accounting:
        assert not quieted and first == fake.parent
        return
    assert quieted and has_shim and first.name.startswith("nirspi-sacct-")
    assert not first.exists()  # removed when the process exited
