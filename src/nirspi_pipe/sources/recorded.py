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
    y = rec.measurements
    t = rec.timestamps
    offset = 0.0
    if subtract_offset and rec.background is not None:
        offset = float(rec.background.mean())
    elif subtract_offset and rec.dark is not None:
        offset = float(rec.dark.mean())
    info: dict[str, Any] = {"measurements_in_file": int(y.size), **rec.meta}
    patterns = None
    gain = rec.gain
    if rec.patterns is None:
        indices = rec.indices
        m = indices.size  # type: ignore[union-attr]
        info.update(patterns_given="spec", split=rec.split, hadamard=True, fast_path=True)
        if rec.split == "differential":
            y_pos, y_neg, times = y, None, t
            offset = 0.0
        elif rec.split == "interleaved":
            y_pos, y_neg = y[0::2] - offset, y[1::2] - offset
            times = _pair_times(t, np.arange(0, 2 * m, 2), np.arange(1, 2 * m, 2))
        else:  # stacked
            y_pos, y_neg = y[:m] - offset, y[m:] - offset
            times = _pair_times(t, np.arange(m), np.arange(m, 2 * m))
    else:
        match = match_hadamard(rec.patterns)
        info.update(
            patterns_given="explicit", pattern_kind=match.kind, hadamard=match.hadamard, fast_path=match.hadamard
        )
        if match.kind == "split":
            pos, neg = match.pos_rows, match.neg_rows
            y_pos, y_neg = y[pos] - offset, y[neg] - offset
            times = _pair_times(t, pos, neg)  # type: ignore[arg-type]
            gain = rec.gain * (match.high - match.low)
        elif match.kind == "signed":
            y_pos, y_neg = match.signs * y, None
            times = t
            gain = rec.gain * match.high
            offset = 0.0
        else:
            y_pos, y_neg, times = y - offset, None, t
            patterns = np.array(rec.patterns, dtype=np.float64)  # a copy (the file may be mapped)
        if match.hadamard:
            indices = match.indices
        else:
            if patterns is None:
                patterns = match.canonical
            indices = np.arange(y_pos.size, dtype=np.int64)
    total = int(y_pos.size)
    if keep is not None and keep < total:
        indices, y_pos = indices[:keep], y_pos[:keep]  # type: ignore[index]
        y_neg = None if y_neg is None else y_neg[:keep]
        times = None if times is None else times[:keep]
        patterns = None if patterns is None else patterns[:keep]
    info["patterns_used"] = int(y_pos.size)
    derived: dict[str, float] = {"offset_subtracted": offset}
    if rec.dark is not None:
        derived["dark_mean"] = float(rec.dark.mean())
    if rec.background is not None:
        derived["background_mean"] = float(rec.background.mean())
    if rec.itof_raw is not None:
        info["itof_raw_shape"] = list(rec.itof_raw.shape)
    return Acquisition(
        n=rec.n,
        indices=np.asarray(indices, dtype=np.int64),
        y_pos=np.asarray(y_pos, dtype=np.float64),
        y_neg=None if y_neg is None else np.asarray(y_neg, dtype=np.float64),
        gain=float(gain),
        truth=_truth(rec, name),
        patterns=patterns,
        timestamps_s=times,
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
