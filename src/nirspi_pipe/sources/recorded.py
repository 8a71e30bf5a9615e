"""Source ``recorded``: an acquisition loaded from an NPZ file (docs/device.md).

The file fixes the patterns and their order, so the scan stage's *order* is ignored. Its
*ratio* is honoured by truncation: with ``scan.ratio = r < 1`` only the first
``round(r · n²)`` measurements of the file (in file order) are used, which is what stopping the
device early would have given (``use_scan_ratio: false`` uses every measurement regardless).

Explicit pattern matrices are inspected (:func:`~nirspi_pipe.device.recording.match_hadamard`):
split ±Hadamard rows in any order become a Hadamard :class:`Acquisition` (``indices``,
``y_pos``/``y_neg``), so the fast ``fwht`` solver applies; other patterns stay explicit in
``Acquisition.patterns`` (``(m, n²)``, ±1-equivalent) for solvers that take a general linear
operator (``lstsq``, ``fista_tv``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from nirspi_pipe.device.recording import Recording, load_recording, match_hadamard
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.orders import n_selected
from nirspi_pipe.stages import ScanIndices
from nirspi_pipe.types import Acquisition, Camera, Scene

__all__ = ["Recorded", "recording_to_acquisition"]


def _truth(rec: Recording, name: str) -> Scene | None:
    """A Scene from the file's ground-truth image. Only radiance is known: depth is ``inf``,
    normals zero, reflectance = radiance (albedo unknown), mask and coverage everywhere."""
    if rec.image is None:
        return None
    n = rec.n
    camera = Camera(resolution=n, fov_deg=rec.fov_deg if rec.fov_deg is not None else Camera.fov_deg)
    return Scene(
        name=name,
        camera=camera,
        radiance=rec.image,
        depth_m=np.full((n, n), np.inf),
        normals=np.zeros((n, n, 3)),
        mask=np.ones((n, n), dtype=bool),
        coverage=np.ones((n, n)),
        reflectance=rec.image.copy(),
        distance_m=float("nan"),
    )


def _pair_times(t: np.ndarray | None, a: np.ndarray, b: np.ndarray | None) -> np.ndarray | None:
    if t is None:
        return None
    return t[a] if b is None else 0.5 * (t[a] + t[b])


@dataclass
class _Readings:
    """A recording's readings as an acquisition takes them (see :func:`recording_to_acquisition`)."""

    indices: Any
    y_pos: np.ndarray
    y_neg: np.ndarray | None
    times: np.ndarray | None
    offset: float
    gain: float
    patterns: np.ndarray | None = None


def _offset(rec: Recording, subtract_offset: bool) -> float:
    """The mean ``background`` (else ``dark``) reading to subtract, or 0."""
    if subtract_offset and rec.background is not None:
        return float(rec.background.mean())
    if subtract_offset and rec.dark is not None:
        return float(rec.dark.mean())
    return 0.0


def _spec_readings(rec: Recording, offset: float, info: dict[str, Any]) -> _Readings:
    """Readings of a recording whose patterns are given by their spec (Hadamard rows)."""
    y, t = rec.measurements, rec.timestamps
    indices = rec.indices
    m = indices.size  # type: ignore[union-attr]
    info.update(patterns_given="spec", split=rec.split, hadamard=True, fast_path=True)
    if rec.split == "differential":
        return _Readings(indices, y, None, t, 0.0, rec.gain)
    if rec.split == "interleaved":
        times = _pair_times(t, np.arange(0, 2 * m, 2), np.arange(1, 2 * m, 2))
        return _Readings(indices, y[0::2] - offset, y[1::2] - offset, times, offset, rec.gain)
    # stacked
    times = _pair_times(t, np.arange(m), np.arange(m, 2 * m))
    return _Readings(indices, y[:m] - offset, y[m:] - offset, times, offset, rec.gain)


def _explicit_readings(rec: Recording, given: np.ndarray, offset: float, info: dict[str, Any]) -> _Readings:
    """Readings of a recording that holds its patterns (``given``): split pairs, signed rows or any others."""
    y, t = rec.measurements, rec.timestamps
    match = match_hadamard(given)
    info.update(patterns_given="explicit", pattern_kind=match.kind, hadamard=match.hadamard, fast_path=match.hadamard)
    if match.kind == "split":
        pos, neg = match.pos_rows, match.neg_rows
        times = _pair_times(t, pos, neg)  # type: ignore[arg-type]
        out = _Readings(None, y[pos] - offset, y[neg] - offset, times, offset, rec.gain * (match.high - match.low))
    elif match.kind == "signed":
        out = _Readings(None, match.signs * y, None, t, 0.0, rec.gain * match.high)
    else:
        patterns = np.array(given, dtype=np.float64)  # a copy (the file may be mapped)
        out = _Readings(None, y - offset, None, t, offset, rec.gain, patterns)
    if match.hadamard:
        out.indices = match.indices
    else:
        if out.patterns is None:
            out.patterns = match.canonical
        out.indices = np.arange(out.y_pos.size, dtype=np.int64)
    return out


def _first(r: _Readings, keep: int) -> _Readings:
    """The first ``keep`` measurements."""
    return _Readings(
        r.indices[:keep],
        r.y_pos[:keep],
        None if r.y_neg is None else r.y_neg[:keep],
        None if r.times is None else r.times[:keep],
        r.offset,
        r.gain,
        None if r.patterns is None else r.patterns[:keep],
    )


def recording_to_acquisition(
    rec: Recording, keep: int | None = None, subtract_offset: bool = True, name: str = "recorded"
) -> Acquisition:
    """Turn a validated recording into an :class:`Acquisition`.

    Args:
        rec: the recording.
        keep: use only the first ``keep`` ±1 measurements (file order); None keeps all.
        subtract_offset: subtract the mean ``background`` (else ``dark``) reading from raw
            readings. Differential readings (``split="differential"``, signed ±1 rows) are left
            alone; in split pairs it cancels anyway.
        name: scene name for the ground truth.
    """
    offset = _offset(rec, subtract_offset)
    info: dict[str, Any] = {"measurements_in_file": int(rec.measurements.size), **rec.meta}
    r = (
        _spec_readings(rec, offset, info)
        if rec.patterns is None
        else _explicit_readings(rec, rec.patterns, offset, info)
    )
    if keep is not None and keep < int(r.y_pos.size):
        r = _first(r, keep)
    info["patterns_used"] = int(r.y_pos.size)
    derived: dict[str, float] = {"offset_subtracted": r.offset}
    if rec.dark is not None:
        derived["dark_mean"] = float(rec.dark.mean())
    if rec.background is not None:
        derived["background_mean"] = float(rec.background.mean())
    if rec.itof_raw is not None:
        info["itof_raw_shape"] = list(rec.itof_raw.shape)
    return Acquisition(
        n=rec.n,
        indices=np.asarray(r.indices, dtype=np.int64),
        y_pos=np.asarray(r.y_pos, dtype=np.float64),
        y_neg=None if r.y_neg is None else np.asarray(r.y_neg, dtype=np.float64),
        gain=float(r.gain),
        truth=_truth(rec, name),
        patterns=r.patterns,
        timestamps_s=r.times,
        derived=derived,
        info=info,
    )


@dataclass(frozen=True)
class Recorded:
    """Source ``recorded``: replay an acquisition file (NPZ, docs/device.md).

    Attributes:
        path: the ``.npz`` file (relative to the working directory).
        subtract_offset: subtract the mean background (else dark) reading from raw readings.
        use_scan_ratio: honour ``scan.ratio`` by keeping only the first ``round(ratio · n²)``
            measurements of the file; false keeps them all.
        scan_indices: resolves the scan option a recording names in its pattern spec
            (``order``); the runner hands it over (:data:`ScanIndices`). None: such a
            recording is refused with a message naming ``order``.
    """

    path: str | None = None
    subtract_offset: bool = True
    use_scan_ratio: bool = True
    scan_indices: ScanIndices | None = field(
        default=None,
        repr=False,
        compare=False,
        metadata={"config": False},  # set by the runner, not a config key
    )

    needs_scene: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if self.path is None or str(self.path).strip() == "":
            raise ConfigError("path", self.path, "an .npz recording (source.path=FILE)")
        if not Path(self.path).is_file():
            raise ConfigError("path", self.path, "an existing .npz file")

    def with_scan_indices(self, resolver: ScanIndices | None) -> Recorded:
        """This source with the runner's resolver of scan options (:class:`~nirspi_pipe.stages.ReadsScanOptions`)."""
        return replace(self, scan_indices=resolver)

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition:
        """Load, validate and convert the recording; ``scene`` and ``rng`` are not used, and of
        ``indices`` only their number (the scan ratio) matters."""
        rec = load_recording(self.path, indices_from_order=self.scan_indices)  # type: ignore[arg-type]
        if rec.n != n:
            warnings.warn(
                f"source: the recording is {rec.n}x{rec.n} but camera.resolution={n}; "
                f"reconstructing at {rec.n}x{rec.n} (set camera.resolution={rec.n})",
                stacklevel=2,
            )
        keep = None
        fraction = len(indices) / float(n * n)
        if self.use_scan_ratio and fraction < 1.0:
            keep = n_selected(fraction, rec.n * rec.n)
        return recording_to_acquisition(rec, keep, self.subtract_offset, name=f"recorded:{Path(self.path).stem}")  # type: ignore[arg-type]
