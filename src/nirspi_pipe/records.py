"""Run records: ``record.json`` beside ``arrays.npz`` and PNGs in each job's output folder.

Record format (one JSON object)::

    {"config":    resolved config (no hydra node),
     "choices":   {group: option} from hydra.runtime.choices (hydra/* groups left out),
     "metrics":   {name: float},
     "timings_ms": {stage: float},            # measured by the runner, "total" included
     "derived":   {name: float},              # physical quantities the source used
     "info":      {stage: {name: value}},     # stage bookkeeping (iterations, stop reason)
     "meta":      {"config_hash", "job_key", "inputs": {key: sha256 of the file it names},
                   "seed", "versions", "nirspi_pipe_version", "git_sha", "git_dirty",
                   "source_hash", "code", "platform", "opencl_devices",
                   "status": "ok" | "failed", "error", "error_type", "exit_code", "signal",
                   "attempt", "warnings", "overrides", "job_num", "started", "wall_s"}}

Every file is strict JSON (RFC 8259: no ``NaN``/``Infinity`` tokens;
:func:`nirspi_pipe.strictjson.dumps_strict`). The result sections never hold a non-finite number
(:mod:`nirspi_pipe.finite` leaves them out, each with its reason); a non-finite number elsewhere,
such as the user's ``fog.extent_mm=inf`` in ``config``, is written as the YAML spelling the
command line and config files accept (:mod:`nirspi_pipe.strictjson`).
:func:`nirspi_pipe.jobkey.config_hash` hashes the same encoding, so the hash of a record's
``config`` read back equals the job's.

The record's parts live in modules named for what they hold: :mod:`nirspi_pipe.strictjson` (the
JSON encoding), :mod:`nirspi_pipe.jobkey` (config hash, input files, job key),
:mod:`nirspi_pipe.outputfiles` (atomic writes, links refused, the job lock) and
:mod:`nirspi_pipe.provenance` (which code ran); this module writes and reads the record and the
arrays beside it.
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.jobkey import InputHasher, config_hash, job_key_of
from nirspi_pipe.outputfiles import atomic_write
from nirspi_pipe.provenance import provenance
from nirspi_pipe.safeio import read_regular, sanitize_text
from nirspi_pipe.strictjson import dumps_strict

__all__ = [
    "PNG_MIN_SIDE",
    "RECORD_NAME",
    "RECORD_READ_LIMIT",
    "new_record",
    "pixel_blocks",
    "read_record",
    "write_arrays",
    "write_record",
]

RECORD_NAME = "record.json"


#: The input files' hashes of this process's jobs, cached by ``(path, size, mtime_ns, inode)``
#: (:class:`InputHasher`): a runner of a sweep whose jobs name one recording reads it once, not
#: once a job; a file replaced or changed in place (new size or mtime) is read again.
_INPUTS = InputHasher()


def new_record(
    config: dict[str, Any],
    choices: Mapping[str, str],
    overrides: list[str],
    job_num: int | None,
    attempt: int | None,
    **meta: Any,
) -> dict[str, Any]:
    """A job's record before its run: the resolved ``config`` and its keys (config hash; job key
    with the sha256 of every input file the config names), :func:`provenance`, empty results and
    ``status: failed`` until the run says otherwise; ``meta`` adds or overrides fields of ``meta``."""
    inputs = _INPUTS.hashes(config)
    hashed = config_hash(config)  # once: it is the job key too when the config names no input file
    return {
        "config": config,
        "choices": dict(choices),
        "metrics": {},
        "timings_ms": {},
        "derived": {},
        "info": {},
        "meta": {
            "config_hash": hashed,
            "job_key": job_key_of(config, inputs, hashed),
            "inputs": inputs,
            **provenance(),
            "status": "failed",
            "error": None,
            "warnings": [],
            "overrides": overrides,
            "job_num": job_num,
            "attempt": attempt,
            **meta,
        },
    }


def write_record(folder: Path, record: Mapping[str, Any]) -> Path:
    """Write ``record.json`` atomically (:func:`atomic_write`: a unique temporary file, then a
    rename), so a killed job or a full disk never leaves a half-written record, and two writers
    never tear each other's. Raises :class:`OutputError` when it cannot be written."""
    text = dumps_strict(record, indent=2)
    return atomic_write(Path(folder) / RECORD_NAME, text)


#: The largest ``record.json`` read back (assumed: about a thousand times the 12 kB a default
#: run's record takes, so that no real record is refused and a planted file costs little).
RECORD_READ_LIMIT = 16 << 20


def read_record(path: Path) -> dict[str, Any]:
    """Read one ``record.json`` (``Infinity``/``NaN`` allowed, as written). A file that is not
    regular (a FIFO, a device: refused without blocking), larger than :data:`RECORD_READ_LIMIT`,
    not JSON, nested too deep, or not an object whose ``meta`` (when present) is an object
    raises a ``ValueError`` naming the file (:class:`nirspi_pipe.safeio.UnsafeInputError` for
    the first two), never blocks."""
    raw = read_regular(path, RECORD_READ_LIMIT, str(path))
    try:
        data = json.loads(raw)
    except RecursionError:
        raise ValueError(f"{sanitize_text(path, 300)}: JSON nested too deep; allowed: a record.json") from None
    if not isinstance(data, dict) or not isinstance(data.get("meta", {}), dict):
        shape = type(data).__name__ if not isinstance(data, dict) else "an object whose meta is not an object"
        raise ValueError(f"{sanitize_text(path, 300)}: {shape}, not a record; allowed: a record.json nirspi-run wrote")
    return data


#: The shortest side a written PNG is blown up to, in screen pixels (assumed: 256 px, a size an
#: image viewer shows at 100 % without squinting; an 8 × 8 image becomes 256 × 256).
PNG_MIN_SIDE = 256


def pixel_blocks(image: np.ndarray, min_side: int = PNG_MIN_SIDE) -> np.ndarray:
    """``image`` (2-D) with each pixel repeated into a k × k block, k the smallest integer that
    makes the shorter side at least ``min_side`` (1 for images that large already): the pixel
    grid drawn as it is, nearest neighbour, no interpolation. Values are not changed."""
    a = np.asarray(image)
    short = min(a.shape[:2]) if a.ndim >= 2 and a.size else 0
    k = max(1, -(-int(min_side) // short)) if short else 1
    return np.repeat(np.repeat(a, k, axis=0), k, axis=1) if k > 1 else a


def write_arrays(
    folder: Path, arrays: Mapping[str, np.ndarray | None], images: Mapping[str, np.ndarray | None]
) -> None:
    """Write ``arrays.npz`` (skipping None entries) and 8-bit grayscale PNGs of ``images``, each
    atomically (:func:`atomic_write`); :class:`OutputError` when a file cannot be written. A PNG
    shows each pixel as a square block (:func:`pixel_blocks`: nearest neighbour, no smoothing), so
    that the device's 8 × 8 image is readable; ``arrays.npz`` keeps the arrays themselves."""
    present = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    if present:
        buf = io.BytesIO()
        np.savez_compressed(buf, **present)  # type: ignore[arg-type]  # numpy stubs type **kwds as allow_pickle
        atomic_write(Path(folder) / "arrays.npz", buf.getvalue())
    if images:
        from matplotlib.image import imsave  # start-up: matplotlib takes ~1 s to import; only the PNGs need it

        for name, img in images.items():
            if img is None:
                continue
            a = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
            buf = io.BytesIO()
            imsave(buf, pixel_blocks(np.clip(a, 0.0, 1.0)), cmap="gray", vmin=0.0, vmax=1.0, format="png")
            atomic_write(Path(folder) / f"{name}.png", buf.getvalue())
