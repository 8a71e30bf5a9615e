"""Run records: ``record.json`` beside ``arrays.npz`` and PNGs in each job's output folder.

Record format (one JSON object)::

    {"config":    resolved config (no hydra node),
     "choices":   {group: option} from hydra.runtime.choices (hydra/* groups left out),
     "metrics":   {name: float},
     "timings_ms": {stage: float},            # measured by the runner, "total" included
     "derived":   {name: float},              # physical quantities the source used
     "info":      {stage: {name: value}},     # stage bookkeeping (iterations, stop reason)
     "meta":      {"config_hash", "seed", "versions", "git_sha", "git_dirty", "platform",
                   "opencl_devices", "status": "ok" | "failed", "error", "error_type",
                   "warnings", "overrides", "job_num", "started", "wall_s"}}
"""

from __future__ import annotations

import hashlib
import json
import math
import platform
import subprocess
from collections.abc import Mapping
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "RECORD_NAME",
    "config_hash",
    "provenance",
    "write_record",
    "read_record",
    "write_arrays",
]

RECORD_NAME = "record.json"

_VERSIONED = (
    "nirspi-pipe",
    "numpy",
    "scipy",
    "hydra-core",
    "omegaconf",
    "pandas",
    "scikit-image",
    "miepython",
    "pyopencl",
)


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and other leaves into JSON-friendly Python values."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value)
    if value is None or isinstance(value, (str, int)):
        return value
    return str(value)


def config_hash(config: Mapping[str, Any]) -> str:
    """Deterministic 16-hex-digit key of a resolved config (sha256 of canonical JSON)."""
    text = json.dumps(_jsonable(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=5, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


@lru_cache(maxsize=4)
def _git_state(start: str) -> tuple[str | None, bool | None]:
    cwd = Path(start)
    sha = _git(["rev-parse", "HEAD"], cwd)
    if not sha:
        return None, None
    status = _git(["status", "--porcelain", "--untracked-files=no"], cwd)
    return sha, bool(status) if status is not None else None


@lru_cache(maxsize=1)
def opencl_devices() -> tuple[str, ...]:
    """``"platform / device"`` names of the OpenCL devices pyopencl sees (empty when none).

    Cached per process: the first call costs the OpenCL platform query (~0.1–0.5 s).
    """
    try:
        import pyopencl as cl

        return tuple(f"{p.name} / {d.name}" for p in cl.get_platforms() for d in p.get_devices())
    except Exception as exc:  # noqa: BLE001 - provenance must never fail a run
        return (f"unavailable: {type(exc).__name__}",)


def provenance(search_dirs: tuple[str, ...] = ()) -> dict[str, Any]:
    """Package versions, platform and the git commit of the code that ran.

    The git SHA is looked up from the installed package's folder (editable installs) and then
    from ``search_dirs`` (e.g. the launch directory); ``None`` when neither is a checkout.
    """
    versions = {}
    for dist in _VERSIONED:
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    versions["python"] = platform.python_version()
    sha = dirty = None
    for start in (str(Path(__file__).resolve().parent), *search_dirs):
        sha, dirty = _git_state(start)
        if sha:
            break
    return {
        "versions": versions,
        "git_sha": sha,
        "git_dirty": dirty,
        "platform": f"{platform.system()}-{platform.machine()} ({platform.platform()})",
        "opencl_devices": list(opencl_devices()),
    }


def write_record(folder: Path, record: Mapping[str, Any]) -> Path:
    """Write ``record.json`` atomically (temp file, then rename) so a killed job never leaves a
    half-written record that looks complete."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / RECORD_NAME
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_jsonable(record), indent=2, allow_nan=True))
    tmp.replace(path)
    return path


def read_record(path: Path) -> dict[str, Any]:
    """Read one ``record.json`` (``Infinity``/``NaN`` allowed, as written)."""
    return json.loads(Path(path).read_text())


def write_arrays(folder: Path, arrays: Mapping[str, np.ndarray | None], images: Mapping[str, np.ndarray | None]) -> None:
    """Write ``arrays.npz`` (skipping None entries) and 8-bit grayscale PNGs of ``images``."""
    folder.mkdir(parents=True, exist_ok=True)
    present = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    if present:
        np.savez_compressed(folder / "arrays.npz", **present)
    if images:
        from matplotlib.image import imsave

        for name, img in images.items():
            if img is None:
                continue
            a = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
            imsave(folder / f"{name}.png", np.clip(a, 0.0, 1.0), cmap="gray", vmin=0.0, vmax=1.0)


def finite_or_none(x: float) -> float | None:
    """``x`` if finite, else None (for text summaries)."""
    return x if math.isfinite(x) else None
