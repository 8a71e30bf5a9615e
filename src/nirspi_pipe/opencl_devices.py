"""Which OpenCL device a stage runs on, and which back end ``auto`` picks (issue 33).

Device spec (the stages' ``device`` key: ``sfs.device``, ``solver.device`` for ``solver=omp``):

* ``auto``: the device named by ``PYOPENCL_CTX`` when that is set (pyopencl's own syntax,
  ``platform[:device]`` by index), else the first GPU with float64, else the first float64
  device of any type;
* ``cpu`` / ``gpu``: the first float64 device of that type (``PYOPENCL_CTX`` is not read);
* ``P:D`` (``0:1``): device ``D`` of platform ``P``, by index as ``clinfo -l`` lists them.

Back end ``auto`` (:func:`choose`): a stage runs on OpenCL where that was *measured* faster than
numpy on this kind of device at this size. The measurements are a table, one row per device,
stage and size, with the faster back end: the package's own (:data:`PACKAGED_ROWS`, measured by
``nirspi-bench gpu``) merged with the user's, which ``nirspi-bench gpu
--write-table`` writes for the machine it runs on (``$NIRSPI_DEVICE_TABLE``, default
``~/.cache/nirspi-pipe/device_table.json``). A size between two measured sizes takes the choice of
the nearest measured one at or below it (the smallest measured one below all of them). Where no
row exists for the device, the rule is the one measured on PoCL's CPU device: SFS on OpenCL (the
serial kernels are compiled loops, 10-40x faster than numpy: docs/sfs.md), OMP on numpy (the
device OMP is slower there: docs/reconstruction.md).

Nothing here imports pyopencl before a function is called.
"""

from __future__ import annotations

import json
import os
import re
from functools import lru_cache
from pathlib import Path
from typing import Any

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.strictjson import dumps_strict

__all__ = [
    "DEVICE_KEYWORDS",
    "check_device",
    "opencl_device",
    "opencl_context",
    "device_label",
    "is_gpu",
    "choose",
    "load_table",
    "table_path",
]

DEVICE_KEYWORDS = ("auto", "cpu", "gpu")
_INDEX = re.compile(r"^\d+:\d+$")

#: Device-independent fallbacks of :func:`choose` by stage, measured on PoCL's CPU device (this
#: project's 2-core machines; ``nirspi-bench sfs``, ``nirspi-bench omp --opencl``).
DEFAULT_CHOICE = {"sfs": "opencl", "omp": "numpy"}

#: Rows shipped with the package, ``{device name: {stage: {size: backend}}}``, each measured by
#: ``nirspi-bench gpu`` on that device (docs/gpu.md says where). Empty until a GPU run is measured:
#: without a row, a GPU gets :data:`DEFAULT_CHOICE` like any device.
PACKAGED_ROWS: dict[str, dict[str, dict[int, str]]] = {}


def check_device(value: Any, key: str = "device") -> str:
    """``value`` as a device spec, or :class:`ConfigError` naming ``key`` and the allowed values."""
    if not isinstance(value, str) or not (value in DEVICE_KEYWORDS or _INDEX.match(value)):
        raise ConfigError(key, value, "auto, cpu, gpu, or <platform>:<device> by index (clinfo -l)")
    return value


def _fp64(device: Any) -> bool:
    return "cl_khr_fp64" in device.extensions


def _devices() -> list[tuple[int, int, Any]]:
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (192 ms here)

    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise NirspiError(f"OpenCL: no platform ({exc}); install an ICD (pocl-opencl-icd, a GPU driver)") from None
    out = []
    for pi, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        out += [(pi, di, d) for di, d in enumerate(devices)]
    return out


def _from_pyopencl_ctx(value: str) -> Any:
    """The device ``PYOPENCL_CTX`` names (``P``, ``P:D``; pyopencl's syntax by index)."""
    parts = value.split(":")
    try:
        pi = int(parts[0])
        di = int(parts[1]) if len(parts) > 1 and parts[1] != "" else 0
    except ValueError:
        raise NirspiError(f"PYOPENCL_CTX={value!r}: expected <platform>[:<device>] by index") from None
    for p, d, dev in _devices():
        if (p, d) == (pi, di):
            return dev
    raise NirspiError(f"PYOPENCL_CTX={value!r}: no such OpenCL device here (clinfo -l lists them)")


@lru_cache(maxsize=8)
def opencl_device(spec: str = "auto") -> Any:
    """The ``pyopencl.Device`` a device spec names (cached per process); :class:`NirspiError`
    (one line) when there is none or it lacks float64."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (192 ms here)

    check_device(spec)
    if spec == "auto" and os.environ.get("PYOPENCL_CTX", "").strip():
        dev = _from_pyopencl_ctx(os.environ["PYOPENCL_CTX"].strip())
    elif _INDEX.match(spec):
        pi, di = (int(x) for x in spec.split(":"))
        found = [d for p, i, d in _devices() if (p, i) == (pi, di)]
        if not found:
            raise NirspiError(f"device={spec!r}: no such OpenCL device here (clinfo -l lists them)")
        dev = found[0]
    else:
        fp64 = [d for _, _, d in _devices() if _fp64(d)]
        gpus = [d for d in fp64 if d.type & cl.device_type.GPU]
        cpus = [d for d in fp64 if d.type & cl.device_type.CPU]
        pick = {"gpu": gpus, "cpu": cpus, "auto": gpus or fp64}[spec]
        if not pick:
            kind = "" if spec == "auto" else f"{spec.upper()} "
            raise NirspiError(f"device={spec!r}: no OpenCL {kind}device with float64 (cl_khr_fp64) here")
        dev = pick[0]
    if not _fp64(dev):
        raise NirspiError(f"device={spec!r}: {dev.name} has no float64 (cl_khr_fp64)")
    return dev


@lru_cache(maxsize=8)
def opencl_context(spec: str = "auto") -> tuple[Any, Any]:
    """``(context, queue)`` on :func:`opencl_device` (one per device spec and process)."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (192 ms here)

    ctx = cl.Context([opencl_device(spec)])
    return ctx, cl.CommandQueue(ctx)


def device_label(device: Any) -> str:
    """``"platform / device (GPU|CPU)"``: what a record names."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (192 ms here)

    kind = "GPU" if device.type & cl.device_type.GPU else "CPU" if device.type & cl.device_type.CPU else "other"
    return f"{device.platform.name.strip()} / {device.name.strip()} ({kind})"


def is_gpu(device: Any) -> bool:
    """True for a GPU device."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (192 ms here)

    return bool(device.type & cl.device_type.GPU)


def table_path() -> Path:
    """The user's measured table: ``$NIRSPI_DEVICE_TABLE`` or ``~/.cache/nirspi-pipe/device_table.json``."""
    env = os.environ.get("NIRSPI_DEVICE_TABLE", "").strip()
    return Path(env).expanduser() if env else Path.home() / ".cache" / "nirspi-pipe" / "device_table.json"


def _read(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


@lru_cache(maxsize=1)
def load_table() -> dict[str, dict[str, dict[int, str]]]:
    """``{device name: {stage: {size: backend}}}``: the packaged rows, then the user's (which win).
    Malformed entries are ignored (a broken cache file must never stop a run)."""
    out: dict[str, dict[str, dict[int, str]]] = {}
    user = _read(table_path()).get("devices", {})
    for source in (PACKAGED_ROWS, user if isinstance(user, dict) else {}):
        for name, stages in source.items():
            if not isinstance(stages, dict):
                continue
            for stage, sizes in stages.items():
                if not isinstance(sizes, dict):
                    continue
                for size, backend in sizes.items():
                    if backend in ("numpy", "opencl") and str(size).isdigit():
                        out.setdefault(str(name), {}).setdefault(str(stage), {})[int(size)] = backend
    return out


def choose(stage: str, device: Any, size: int) -> tuple[str, str]:
    """``(backend, why)`` for back end ``auto`` of ``stage`` (``sfs``, ``omp``) at image side
    ``size`` on ``device``: the measured table's choice (see the module docstring), else
    :data:`DEFAULT_CHOICE`. ``why`` says which, for the record."""
    rows = load_table().get(device.name.strip(), {}).get(stage, {})
    if rows:
        below = [s for s in rows if s <= size]
        pick = max(below) if below else min(rows)
        return rows[pick], f"measured on {device.name.strip()} at {pick}²"
    return DEFAULT_CHOICE[stage], "default (measured on PoCL's CPU device)"


def write_table(rows: dict[str, dict[str, dict[int, str]]], path: Path | None = None) -> Path:
    """Merge measured ``rows`` into the user's table file (the ``nirspi-bench gpu`` output)."""
    path = path or table_path()
    data = _read(path)
    devices = data.setdefault("devices", {})
    for name, stages in rows.items():
        for stage, sizes in stages.items():
            devices.setdefault(name, {}).setdefault(stage, {}).update({str(k): v for k, v in sizes.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dumps_strict(data, indent=1, sort_keys=True) + "\n")
    load_table.cache_clear()
    return path
