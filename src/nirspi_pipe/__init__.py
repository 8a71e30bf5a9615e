"""nirspi-pipe: near-infrared single-pixel imaging (NIR-SPI) in fog.

Simulate or replay a single-pixel camera (Hadamard-patterned 1550 nm illumination, an InGaAs
photodiode and four CW iToF lasers), reconstruct 2D images and 3D meshes, and sweep over fog,
background light and scan order with Hydra. See README.md and docs/api.md.

The Python API (imported on first use, so ``import nirspi_pipe`` stays cheap)::

    result = nirspi_pipe.run(["fog=chamber", "scan=spiral"])   # a RunResult
    frame = nirspi_pipe.load_results("sweeps/scan")              # a sweep's pandas DataFrame
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["BadOverrides", "BadResults", "RunFailed", "RunResult", "__version__", "compose", "load_results", "run"]

if TYPE_CHECKING:
    from nirspi_pipe.app.api import (
        BadOverrides,
        BadResults,
        RunFailed,
        RunResult,
        compose,
        load_results,
        run,
    )


def __getattr__(name: str) -> Any:
    """Lazy exports of :mod:`nirspi_pipe.app.api` (PEP 562)."""
    if name in __all__ and name != "__version__":
        from nirspi_pipe.app import api  # start-up: loads 19 modules of ours (16 ms here)

        return getattr(api, name)
    raise AttributeError(f"module 'nirspi_pipe' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
