"""Hydra's logging presets run (helper k3 found ``hydra/job_logging=stdout`` and ``=disabled`` ending
in a traceback: config.yaml patched ``hydra.job_logging.handlers.file.delay`` into every preset,
giving those without a file handler a handler 'file' with no class). The project's own preset
(conf/hydra/job_logging/nirspi.yaml, the default) keeps issue 34's promise: no empty cli.log."""

from __future__ import annotations

import pytest

FAST = ["preset=null", "camera.resolution=16", "output.quiet=true", "output.images=false"]


@pytest.mark.parametrize("preset", ["stdout", "disabled"])  # the two that crashed; tests/test_api.py runs the default
def test_every_logging_preset_runs(cli, preset: str) -> None:
    out = cli.cwd / "run"
    done = cli("nirspi-run", f"hydra/job_logging={preset}", f"hydra.run.dir={out}", *FAST)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and (out / "record.json").is_file()
    assert not (out / "cli.log").exists()  # neither preset has a file handler
