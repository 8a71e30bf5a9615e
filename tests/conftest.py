"""Shared fixtures: the installed console scripts, run in subprocesses from a temp folder."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import settings

# The default suite draws the same hypothesis examples on every run and machine (CI must not pass or
# fail by luck); `HYPOTHESIS_PROFILE=explore pytest` draws new ones, as the fuzz tests that found the
# ZIP-version and malformed-PLY cases did.
settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

#: Overrides for the noise-free scene. The default run is the paper's fog chamber with 15 kLux of
#: background light and the InGaAs detector; tests of exactness and of the algorithms start here.
NOISE_FREE = ["fog=none", "illumination=none", "detector=ideal"]


def script(name: str) -> str:
    """Path of an installed console script of this environment (next to the interpreter)."""
    candidate = Path(sys.executable).parent / name
    if candidate.exists():
        return str(candidate)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"console script {name} is not installed; run `pip install .` first")
    return found


def load_script(path: Path, name: str) -> Iterator[ModuleType]:
    """A fixture body: the experiment script at ``path`` imported as module ``name`` (registered in
    ``sys.modules`` while the fixture lives: dataclasses look their module up), removed after."""
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(name, None)


def run_cli(args: list[str], cwd: Path, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    """Run a console script (``args[0]``) with the rest as arguments, capturing text output."""
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    env["MPLBACKEND"] = "Agg"
    return subprocess.run(
        [script(args[0]), *args[1:]], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
    )


@pytest.fixture
def cli(tmp_path: Path):
    """Run ``nirspi-*`` commands from an empty temporary directory."""

    def _run(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
        return run_cli(list(args), tmp_path, timeout)

    _run.cwd = tmp_path  # type: ignore[attr-defined]
    return _run


def crash_as(how: str) -> None:
    """Die the way ``how`` names (for crash-isolation tests): ``segv`` (segmentation fault),
    ``exit`` (``os._exit(5)``), ``kill`` (``SIGKILL``), ``raise`` (an exception); ``ok`` returns."""
    import ctypes
    import faulthandler
    import signal

    if how == "segv":
        # pytest enables faulthandler and a forked child inherits it: its "Fatal Python error:
        # Segmentation fault" dump of this deliberate crash would land in the test log. Only this
        # child stops dumping; it still dies of SIGSEGV, which the tests check.
        faulthandler.disable()
        ctypes.string_at(0)
    elif how == "exit":
        os._exit(5)
    elif how == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    elif how == "raise":
        raise RuntimeError("runner broke")
