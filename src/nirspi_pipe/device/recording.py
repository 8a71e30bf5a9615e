"""Recorded acquisitions: the NPZ file format, its validation, and its conversion to an
:class:`~nirspi_pipe.types.Acquisition` (with the fast Hadamard path recognised).

The format is described in docs/device.md. In short, an ``.npz`` (``numpy.savez``, compressed
or not; never pickled objects) with

required
    ``measurements`` ``(M,)`` float: one detector reading per displayed pattern, in the order
    they were displayed; and the patterns, in one of two forms:

    * ``patterns`` ``(M, N)`` float (integer or bool accepted): one row per displayed pattern,
      pixels in row-major order, ``N = n²``; or
    * a pattern spec: ``basis`` (``"hadamard"``), ``resolution`` (``n``), ``split``
      (``"differential"``: one ±1 reading per pattern; ``"interleaved"``: pos, neg, pos, neg …;
      ``"stacked"``: all positive halves, then all negative ones) and either ``indices``
      (``(m,)`` int flat indices ``k = i·n + j``, see :mod:`nirspi_pipe.patterns.hadamard`)
      or ``order`` (the name of a nirspi-pipe scan option, ``"basic"`` …) with optional
      ``ratio`` (default 1).
optional
    ``timestamps`` ``(M,)`` seconds; ``dark`` and ``background`` ``(K,)`` readings with the
    light source off (dark) or off with ambient light on (background); ``itof_raw`` (any
    shape) raw iToF samples; ``image`` ``(n, n)`` ground-truth relative radiance; ``gain``
    detector units per unit relative radiance per pixel (default 1); ``fov_deg``; ``units``
    and ``device`` (strings); ``format_version`` (1).

Every problem raises :class:`RecordingError` with one line naming the key.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.patterns.hadamard import is_power_of_two, sylvester
from nirspi_pipe.safeio import max_safe_reading, read_npz, sanitize_text

__all__ = [
    "FORMAT_VERSION",
    "SPLITS",
    "RecordingError",
    "Recording",
    "HadamardMatch",
    "load_recording",
    "validate_recording",
    "save_recording",
    "match_hadamard",
]

FORMAT_VERSION = 1
SPLITS = ("differential", "interleaved", "stacked")
_STRING_KEYS = ("basis", "split", "order", "units", "device")
_SPEC_KEYS = ("basis", "resolution", "split", "indices", "order", "ratio")
_OPTIONAL = (
    "timestamps",
    "dark",
    "background",
    "itof_raw",
    "image",
    "gain",
    "fov_deg",
    "units",
    "device",
    "format_version",
)
KNOWN_KEYS = frozenset(("measurements", "patterns", *_SPEC_KEYS, *_OPTIONAL))


class RecordingError(NirspiError, ValueError):
    """A recorded acquisition is malformed; the message names the offending key."""

    def __init__(self, key: str, problem: str, where: str = "") -> None:
        self.key = key
        prefix = f"{where}: " if where else ""
        super().__init__(f"{prefix}key '{key}': {problem}")


@dataclass(frozen=True)
class Recording:
    """A validated recording (arrays as stored; nothing converted yet).

    Exactly one of ``patterns`` and ``indices`` is set (the spec's ``order`` is resolved to
    ``indices`` by :func:`nirspi_pipe.sources.recorded` before this is built).
    """

    measurements: np.ndarray
    n: int
    patterns: np.ndarray | None = None
    indices: np.ndarray | None = None
    split: str | None = None
    timestamps: np.ndarray | None = None
    dark: np.ndarray | None = None
    background: np.ndarray | None = None
    itof_raw: np.ndarray | None = None
    image: np.ndarray | None = None
    gain: float = 1.0
    fov_deg: float | None = None
    meta: dict[str, Any] = field(default_factory=dict)


def _fail(key: str, problem: str, where: str) -> RecordingError:
    return RecordingError(key, problem, where)


def _read_npz(path: Path, where: str) -> dict[str, np.ndarray]:
    """All arrays of an NPZ, read within the memory budget and never unpickled
    (:func:`nirspi_pipe.safeio.read_npz`); uncompressed members are memory-mapped. Each failure
    names the file and the key."""
    if not path.is_file():
        raise _fail("path", "file does not exist", where)
    return read_npz(path, where)


def _string(arrays: dict[str, np.ndarray], key: str, where: str) -> str | None:
    if key not in arrays:
        return None
    a = arrays[key]
    if a.ndim != 0 or a.dtype.kind not in "US":
        raise _fail(key, f"expected a string, got {a.dtype} array of shape {a.shape}", where)
    v = a.item()
    return v.decode() if isinstance(v, bytes) else str(v)


def _scalar(arrays: dict[str, np.ndarray], key: str, where: str, kinds: str = "fiu") -> float | None:
    if key not in arrays:
        return None
    a = arrays[key]
    if a.size != 1 or a.ndim > 1 or a.dtype.kind not in kinds:
        raise _fail(key, f"expected a single number, got {a.dtype} array of shape {a.shape}", where)
    v = float(a.reshape(()).item())
    if not np.isfinite(v):
        raise _fail(key, f"must be finite, got {v}", where)
    return v


def _float_array(a: np.ndarray, key: str, where: str, ndim: int | None, kinds: str = "f") -> np.ndarray:
    if a.dtype.kind not in kinds:
        allowed = {"f": "float", "fiub": "float, integer or bool"}.get(kinds, kinds)
        raise _fail(key, f"dtype {a.dtype} is not allowed (expected {allowed})", where)
    if ndim is not None and a.ndim != ndim:
        raise _fail(key, f"expected {ndim} dimension(s), got shape {a.shape}", where)
    out = np.array(a, dtype=np.float64)  # a copy: the file may be memory-mapped
    bad = ~np.isfinite(out)
    if bad.any():
        first = np.unravel_index(int(np.argmax(bad)), out.shape)
        raise _fail(
            key,
            f"{int(bad.sum())} non-finite value(s) (NaN or Inf), first at index {tuple(int(i) for i in first)}",
            where,
        )
    return out


def _check_magnitudes(y: np.ndarray, gain: float, n: int, optional: dict[str, Any], where: str) -> None:
    """Readings (and offsets, and the truth image) so large that the reconstruction or its
    metrics would overflow float64 are refused (:func:`~nirspi_pipe.safeio.max_safe_reading`)."""
    limit = max_safe_reading(y.size, n * n)
    for key, arr, scale in (
        ("measurements", y, gain),
        ("dark", optional.get("dark"), gain),
        ("background", optional.get("background"), gain),
        ("image", optional.get("image"), 1.0),
    ):
        if arr is None or arr.size == 0:
            continue
        peak = float(np.max(np.abs(arr)))
        if peak / scale > limit or not np.isfinite(peak / scale):
            per = "|value| / gain" if scale != 1.0 or key != "image" else "|value|"
            raise _fail(
                key,
                f"{per} reaches {peak / scale:.3g}; the reconstruction would overflow float64 "
                f"(at most {limit:.3g} for {y.size} readings of {n}x{n})",
                where,
            )


def validate_recording(arrays: dict[str, np.ndarray], where: str = "", indices_from_order: Any = None) -> Recording:
    """Check every key, shape, dtype and value of a recording's arrays and return it.

    ``indices_from_order(order, ratio, n) -> indices`` resolves a spec's ``order`` name (the
    recorded source passes one that builds nirspi-pipe's scan option); without it, ``order``
    is refused. Raises :class:`RecordingError` naming the key.
    """
    unknown = sorted(set(arrays) - KNOWN_KEYS)
    if unknown:
        warnings.warn(f"{where}: ignoring unknown key(s) {sanitize_text(', '.join(unknown))}", stacklevel=2)
    version = _scalar(arrays, "format_version", where, "iu")
    if version is not None and int(version) > FORMAT_VERSION:
        raise _fail("format_version", f"{int(version)} is newer than this reader ({FORMAT_VERSION})", where)
    y = _measurements(arrays, where)
    spec_given = [k for k in _SPEC_KEYS if k in arrays]
    patterns = indices = None
    split: str | None = None
    if "patterns" in arrays:
        if spec_given:
            raise _fail(
                "patterns",
                f"give either 'patterns' or a pattern spec, not both (also found {', '.join(spec_given)})",
                where,
            )
        patterns, n = _pattern_matrix(arrays["patterns"], y, where)
    else:
        n, split, indices = _pattern_spec(arrays, y, spec_given, where, indices_from_order)
    optional = _optional_arrays(arrays, y, n, where)
    gain = _scalar(arrays, "gain", where)
    if gain is not None and gain <= 0:
        raise _fail("gain", f"must be > 0, got {gain}", where)
    fov = _scalar(arrays, "fov_deg", where)
    if fov is not None and not 0 < fov < 170:
        raise _fail("fov_deg", f"{fov} is not in (0, 170) degrees", where)
    _check_magnitudes(y, 1.0 if gain is None else gain, n, optional, where)
    meta = {k: sanitize_text(v, 100) for k in ("units", "device") if (v := _string(arrays, k, where)) is not None}
    return Recording(
        measurements=y,
        n=n,
        patterns=patterns,
        indices=indices,
        split=split,
        gain=1.0 if gain is None else gain,
        fov_deg=fov,
        meta=meta,
        **optional,
    )


def _measurements(arrays: dict[str, np.ndarray], where: str) -> np.ndarray:
    """The detector readings: present, a 1-D finite float array, not empty."""
    if "measurements" not in arrays:
        raise _fail("measurements", "missing (one detector reading per displayed pattern)", where)
    y = _float_array(arrays["measurements"], "measurements", where, ndim=1)
    if y.size == 0:
        raise _fail("measurements", "is empty", where)
    return y


def _pattern_matrix(patterns: np.ndarray, y: np.ndarray, where: str) -> tuple[np.ndarray, int]:
    """An explicit ``(M, n²)`` pattern matrix, one row per reading, and its ``n``."""
    if patterns.dtype.kind not in "fiub":
        raise _fail("patterns", f"dtype {patterns.dtype} is not allowed (expected float, integer or bool)", where)
    if patterns.ndim != 2:
        raise _fail("patterns", f"expected a 2-D (M, N) matrix, got shape {patterns.shape}", where)
    m, big_n = patterns.shape
    if m != y.size:
        raise _fail("patterns", f"has {m} rows but 'measurements' has {y.size} values (one row per reading)", where)
    n = int(round(np.sqrt(big_n)))
    if n * n != big_n or not is_power_of_two(n) or n < 2:
        raise _fail("patterns", f"rows have {big_n} pixels; expected n² pixels with n a power of two ≥ 2", where)
    # min and max are finite exactly when every value is (NaN propagates); no temporary.
    if patterns.dtype.kind == "f" and not (np.isfinite(patterns.min()) and np.isfinite(patterns.max())):
        bad = ~np.isfinite(patterns)
        raise _fail("patterns", f"{int(bad.sum())} non-finite value(s) (NaN or Inf)", where)
    return patterns, n


def _pattern_spec(
    arrays: dict[str, np.ndarray], y: np.ndarray, spec_given: list[str], where: str, indices_from_order: Any
) -> tuple[int, str, np.ndarray]:
    """A Hadamard pattern spec (basis, resolution, split, and indices or order): ``(n, split, indices)``,
    with as many readings as the split needs."""
    missing = [k for k in ("basis", "resolution", "split") if k not in arrays]
    if missing and not spec_given:
        raise _fail(
            "patterns",
            "missing: give 'patterns' (M, N) or a pattern spec (basis, resolution, split, indices or order)",
            where,
        )
    if missing:
        raise _fail(missing[0], "missing from the pattern spec (basis, resolution, split, indices or order)", where)
    basis = _string(arrays, "basis", where)
    if basis != "hadamard":
        raise _fail("basis", f"{basis!r} is not supported; allowed: 'hadamard'", where)
    n = int(_scalar(arrays, "resolution", where, "iu"))  # type: ignore[arg-type]
    if not is_power_of_two(n) or not 2 <= n <= 4096:
        raise _fail("resolution", f"{n} is not a power of two from 2 to 4096", where)
    split = _string(arrays, "split", where)
    if split not in SPLITS:
        raise _fail("split", f"{split!r} is not allowed; allowed: {', '.join(SPLITS)}", where)
    indices = _spec_indices(arrays, n, where, indices_from_order)
    per = 1 if split == "differential" else 2
    if y.size != per * indices.size:
        raise _fail(
            "measurements",
            f"has {y.size} values; split={split!r} with {indices.size} patterns needs {per * indices.size}",
            where,
        )
    return n, split, indices


def _spec_indices(arrays: dict[str, np.ndarray], n: int, where: str, indices_from_order: Any) -> np.ndarray:
    """The spec's pattern indices: explicit ``indices``, or the scan option ``order`` at ``ratio``
    resolved by ``indices_from_order``; distinct, in ``[0, n²)``."""
    if "indices" in arrays:
        if "order" in arrays:
            raise _fail("order", "give either 'indices' or 'order', not both", where)
        idx = arrays["indices"]
        if idx.dtype.kind not in "iu" or idx.ndim != 1:
            raise _fail("indices", f"expected a 1-D integer array, got {idx.dtype} of shape {idx.shape}", where)
        indices = idx.astype(np.int64)
    elif "order" in arrays:
        order = _string(arrays, "order", where)
        ratio = _scalar(arrays, "ratio", where)
        ratio = 1.0 if ratio is None else ratio
        if not 0 < ratio <= 1:
            raise _fail("ratio", f"{ratio} is not a fraction in (0, 1]", where)
        if indices_from_order is None:
            raise _fail("order", "cannot be resolved here; store explicit 'indices'", where)
        indices = np.asarray(indices_from_order(order, ratio, n), dtype=np.int64)
    else:
        raise _fail("indices", "missing from the pattern spec (give 'indices' or 'order')", where)
    if indices.size == 0:
        raise _fail("indices", "is empty", where)
    if indices.min() < 0 or indices.max() >= n * n:
        raise _fail("indices", f"values must lie in [0, {n * n}) for resolution {n}", where)
    if np.unique(indices).size != indices.size:
        raise _fail("indices", "contains repeated pattern indices", where)
    return indices


def _optional_arrays(arrays: dict[str, np.ndarray], y: np.ndarray, n: int, where: str) -> dict[str, Any]:
    """The optional arrays that are present: timestamps (one per reading, not decreasing), dark and
    background readings, raw iToF data and the truth image (``n × n``)."""
    optional: dict[str, Any] = {}
    if "timestamps" in arrays:
        t = _float_array(arrays["timestamps"], "timestamps", where, ndim=1, kinds="fiu")
        if t.size != y.size:
            raise _fail("timestamps", f"has {t.size} values, 'measurements' has {y.size}", where)
        if np.any(np.diff(t) < 0):
            raise _fail("timestamps", "must not decrease", where)
        optional["timestamps"] = t
    for key in ("dark", "background"):
        if key in arrays:
            a = _float_array(arrays[key], key, where, ndim=None)
            if a.size == 0:
                raise _fail(key, "is empty", where)
            optional[key] = a.ravel()
    if "itof_raw" in arrays:
        optional["itof_raw"] = _float_array(arrays["itof_raw"], "itof_raw", where, ndim=None, kinds="fiu")
    if "image" in arrays:
        img = _float_array(arrays["image"], "image", where, ndim=2)
        if img.shape != (n, n):
            raise _fail("image", f"shape {img.shape} does not match the {n}x{n} patterns", where)
        optional["image"] = img
    return optional


def load_recording(path: str | Path, indices_from_order: Any = None) -> Recording:
    """Load and validate a recording (``np.load(..., allow_pickle=False)``)."""
    where = f"recording {path}"
    return validate_recording(_read_npz(Path(path), where), where, indices_from_order)


def save_recording(path: str | Path, compressed: bool = False, **arrays: Any) -> Path:
    """Write a recording after validating it (so a file this writes is always readable).

    Keyword arguments are the format's keys; strings are stored as 0-d unicode arrays. Returns
    the path written. ``order`` cannot be validated here; store ``indices`` instead.
    """
    # Any: numpy types savez(**kwds) as arrays or allow_pickle: bool, so a dict of arrays does not fit it
    stored: dict[str, Any] = {
        k: (np.array(v) if isinstance(v, str) else np.asarray(v)) for k, v in arrays.items() if v is not None
    }
    stored.setdefault("format_version", np.array(FORMAT_VERSION))
    validate_recording(stored, f"save_recording({path})")
    path = Path(path)
    (np.savez_compressed if compressed else np.savez)(path, **stored)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


@dataclass(frozen=True)
class HadamardMatch:
    """Result of :func:`match_hadamard` on an explicit pattern matrix.

    Attributes:
        kind: ``"split"`` (complementary pairs), ``"signed"`` (one ±1 row per pattern),
            ``"binary"`` (two-level rows, neither paired nor signed) or ``"general"``.
        hadamard: whether the (canonical) rows are 2D Sylvester Hadamard patterns.
        indices: ``(m,)`` Hadamard flat index of each measured pattern (hadamard only).
        pos_rows, neg_rows: row numbers of the positive/negative halves (split), or the row of
            each pattern (signed; ``neg_rows`` None). Ordered by first appearance.
        signs: ``(m,)`` ±1: row = sign × canonical pattern (signed only).
        canonical: ``(m, N)`` ±1 canonical patterns (first pixel +1), None when hadamard.
        low, high: the two levels of a two-level matrix.
    """

    kind: str
    hadamard: bool = False
    indices: np.ndarray | None = None
    pos_rows: np.ndarray | None = None
    neg_rows: np.ndarray | None = None
    signs: np.ndarray | None = None
    canonical: np.ndarray | None = None
    low: float = 0.0
    high: float = 1.0


def _hadamard_indices(plus: np.ndarray, n: int, chunk: int = 512) -> np.ndarray | None:
    """Flat indices ``k`` of rows that are 2D Sylvester patterns, or None when any row is not.

    ``plus`` is ``(m, N)`` bool (True where the canonical ±1 row is +1; its first pixel is +1).
    Sylvester row ``k`` has ``H[k, x] = (−1)^popcount(k & x)``, so bit ``b`` of ``k`` is read off
    pixel ``x = 2^b`` (O(m log N)); each row is then compared with the pattern it names, built
    as the Kronecker product of two rows of ``H_n`` (O(m N) in all, no ``N × N`` matrix).
    """
    m, big_n = plus.shape
    bits = big_n.bit_length() - 1
    k = np.zeros(m, dtype=np.int64)
    for b in range(bits):
        k |= (~plus[:, 1 << b]).astype(np.int64) << b
    hpos = sylvester(n) > 0
    i, j = k // n, k % n
    for s in range(0, m, chunk):
        sl = slice(s, s + chunk)
        expected = hpos[i[sl]][:, :, None] == hpos[j[sl]][:, None, :]
        if not np.array_equal(expected.reshape(-1, big_n), plus[sl]):
            return None
    return k


def match_hadamard(patterns: np.ndarray) -> HadamardMatch:
    """Recognise explicit patterns: two-level rows, complementary (split) pairs, and whether
    they are Hadamard patterns in any order. Cost O(M N) plus a sort of M row hashes.

    A two-level row ``r = low + (high − low)·b`` (``b`` 0/1) is the ±1 pattern ``s = 2b − 1``
    shown in the split convention; two rows with ``s`` and ``−s`` are a complementary pair and
    their readings differ by ``(high − low) · Σ s ⊙ O``.
    """
    m, big_n = patterns.shape
    n = int(round(np.sqrt(big_n)))
    low, high = patterns.min(), patterns.max()
    if high == low != 0:  # every row the constant a = |a|·sign(a)·h_0: signed DC rows
        low, high = -abs(high), abs(high)
    if not high > low:
        return HadamardMatch("general")
    plus = patterns == high
    if np.count_nonzero(plus) + np.count_nonzero(patterns == low) != patterns.size:
        return HadamardMatch("general")
    low, high = float(low), float(high)
    first = plus[:, 0].copy()
    np.logical_xor(plus, ~first[:, None], out=plus)  # canonical: every row starts with +1
    packed = np.packbits(plus, axis=1)
    keys = np.ascontiguousarray(packed).view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    rows = np.arange(m)
    if np.all(counts == 2):
        pos = np.full(counts.size, -1)
        neg = np.full(counts.size, -1)
        pos[inverse[first]] = rows[first]
        neg[inverse[~first]] = rows[~first]
        if (pos < 0).any() or (neg < 0).any():
            return HadamardMatch("binary", low=low, high=high)
        order = np.argsort(np.minimum(pos, neg), kind="stable")
        pos, neg = pos[order], neg[order]
        k = _hadamard_indices(plus[pos], n)
        if k is not None:
            return HadamardMatch("split", True, indices=k, pos_rows=pos, neg_rows=neg, low=low, high=high)
        return HadamardMatch(
            "split", pos_rows=pos, neg_rows=neg, canonical=np.where(plus[pos], 1.0, -1.0), low=low, high=high
        )
    if np.all(counts == 1) and low == -high:
        signs = np.where(first, 1.0, -1.0)
        k = _hadamard_indices(plus, n)
        if k is not None:
            return HadamardMatch("signed", True, indices=k, pos_rows=rows, signs=signs, low=low, high=high)
        return HadamardMatch(
            "signed", pos_rows=rows, signs=signs, canonical=np.where(plus, 1.0, -1.0), low=low, high=high
        )
    return HadamardMatch("binary", low=low, high=high)
