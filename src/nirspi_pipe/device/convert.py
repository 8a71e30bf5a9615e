"""``nirspi-convert``: bring other SPI toolboxes' acquisitions into the recorded NPZ format.

Toolboxes store split (positive/negative) acquisitions in several ways; :func:`convert` takes
any of them with the patterns they were measured with and returns the arrays of a recording
(docs/device.md):

* ``pos`` and ``neg``: two ``(m,)`` arrays, the readings of the positive and negative halves of
  pattern ``r`` (the patterns given as ``m`` ±1 rows, or as their ``m`` positive 0/1 halves);
* ``interleaved``: one ``(2m,)`` array ``pos₀, neg₀, pos₁, …`` (patterns as above);
* ``differential``: ``(m,)`` readings ``pos − neg`` already subtracted (±1 patterns);
* ``measurements``: one reading per displayed pattern, with the displayed patterns (``(M, N)``,
  complementary halves as separate rows): repackaged as they are.

Patterns may be ``(m, N)`` rows or an ``(m, n, n)`` image stack (``--stack-last``: MATLAB's
``(n, n, m)``); ``flatten="F"`` reads rows that were flattened column-major (MATLAB's ``P(:)``),
so that images are not transposed. When
the patterns are 2D Hadamard patterns (any order) the output uses the compact pattern spec
(``basis``, ``resolution``, ``split``, ``indices``) instead of the matrix.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.device.recording import RecordingError, match_hadamard, save_recording
from nirspi_pipe.errors import NirspiError
from nirspi_pipe.safeio import open_regular, read_npz

__all__ = ["convert", "load_any", "main"]


def _rows(patterns: np.ndarray, flatten: str) -> np.ndarray:
    p = np.asarray(patterns)
    if p.dtype.kind not in "fiub":
        raise RecordingError("patterns", f"dtype {p.dtype} is not numeric")
    if p.ndim == 3:
        if p.shape[1] != p.shape[2]:
            raise RecordingError("patterns", f"image stack {p.shape} is not (m, n, n)")
        return p.reshape(p.shape[0], -1)  # each image row-major, whatever produced the stack
    if p.ndim != 2:
        raise RecordingError("patterns", f"expected (m, N) rows or (m, n, n) images, got {p.shape}")
    if flatten == "F":
        n = int(round(np.sqrt(p.shape[1])))
        return p.reshape(p.shape[0], n, n, order="F").reshape(p.shape[0], -1)
    return p


def _signed(rows: np.ndarray) -> np.ndarray:
    """±1 form of rows given as ±1 or as positive 0/1 halves."""
    lo, hi = rows.min(), rows.max()
    if lo == -1 and hi == 1 and np.all(np.abs(rows) == 1):
        return rows.astype(np.float64)
    if lo >= 0 and hi > lo and np.all((rows == lo) | (rows == hi)):
        return np.where(rows == hi, 1.0, -1.0)
    raise RecordingError("patterns", "split readings need ±1 rows or their two-level positive halves")


def _vector(a: Any, key: str) -> np.ndarray:
    v = np.asarray(a)
    if v.dtype.kind not in "fiu":
        raise RecordingError(key, f"dtype {v.dtype} is not numeric")
    return v.astype(np.float64).ravel()


def _split_readings(m: int, pos: Any, neg: Any, interleaved: Any, differential: Any) -> tuple[np.ndarray, str]:
    """The readings in one vector and their layout (``stacked``, ``interleaved`` or
    ``differential``), checked against the ``m`` patterns."""
    if pos is not None:
        yp, yn = _vector(pos, "pos"), _vector(neg, "neg")
        if yp.size != m or yn.size != m:
            raise RecordingError("pos", f"pos ({yp.size}) and neg ({yn.size}) need one value per pattern ({m})")
        return np.concatenate([yp, yn]), "stacked"
    if interleaved is not None:
        y = _vector(interleaved, "interleaved")
        if y.size != 2 * m:
            raise RecordingError("interleaved", f"has {y.size} values, {m} patterns need {2 * m}")
        return y, "interleaved"
    y = _vector(differential, "differential")
    if y.size != m:
        raise RecordingError("differential", f"has {y.size} values for {m} patterns")
    return y, "differential"


def _flipped(y: np.ndarray, split: str, flip: np.ndarray, m: int) -> np.ndarray:
    """The readings of rows stored as −h_k made those of +h_k: the halves swapped, or the
    difference negated."""
    if split == "differential":
        return y * flip
    pair = y.reshape(2, m) if split == "stacked" else y.reshape(m, 2).T
    pos_y = np.where(flip > 0, pair[0], pair[1])
    neg_y = np.where(flip > 0, pair[1], pair[0])
    return np.concatenate([pos_y, neg_y]) if split == "stacked" else np.column_stack([pos_y, neg_y]).ravel()


def _explicit_halves(signed: np.ndarray, split: str, m: int) -> np.ndarray:
    """The patterns as stored for non-Hadamard rows: the ±1 rows for differential readings,
    else their two positive halves in the readings' layout."""
    if split == "differential":
        return signed
    return (
        np.concatenate([(1 + signed) / 2, (1 - signed) / 2])
        if split == "stacked"
        else np.stack([(1 + signed) / 2, (1 - signed) / 2], axis=1).reshape(2 * m, -1)
    )


def convert(
    patterns: np.ndarray,
    pos: Any = None,
    neg: Any = None,
    interleaved: Any = None,
    differential: Any = None,
    measurements: Any = None,
    flatten: str = "C",
    **extra: Any,
) -> dict[str, Any]:
    """Arrays of a recording from another toolbox's split acquisition (see the module doc).

    ``extra`` keys (``image``, ``timestamps``, ``gain``, ``device``, …) are passed through.
    ``flatten`` applies to 2-D pattern rows only (an image stack is unambiguous).
    """
    if flatten not in ("C", "F"):
        raise ValueError("flatten must be 'C' (row-major) or 'F' (column-major)")
    given = [
        k
        for k, v in (
            ("pos", pos),
            ("interleaved", interleaved),
            ("differential", differential),
            ("measurements", measurements),
        )
        if v is not None
    ]
    if len(given) != 1 or (pos is None) != (neg is None):
        raise RecordingError("measurements", "give exactly one of pos+neg, interleaved, differential, measurements")
    rows = _rows(patterns, flatten)
    out: dict[str, Any] = dict(extra)
    if measurements is not None:
        out.update(measurements=_vector(measurements, "measurements"), patterns=rows)
        return out
    signed = _signed(rows)
    m = signed.shape[0]
    y, split = _split_readings(m, pos, neg, interleaved, differential)
    match = match_hadamard(signed)
    n = int(round(np.sqrt(signed.shape[1])))
    if match.hadamard and match.kind == "signed" and match.signs is not None:  # signs: set for every signed match
        y = _flipped(y, split, match.signs, m)
        out.update(measurements=y, basis="hadamard", resolution=n, split=split, indices=match.indices)
        return out
    out.update(measurements=y, patterns=_explicit_halves(signed, split, m))
    return out


def load_any(path: Path) -> dict[str, np.ndarray]:
    """Arrays of an ``.npz`` (no pickle) or a MATLAB ``.mat`` file (scipy.io)."""
    if path.suffix.lower() == ".mat":
        from scipy.io import loadmat  # start-up: loads scipy and numpy (714 ms here)

        with open_regular(path) as fh:  # a regular file only: a FIFO or device is refused, never read
            return {k: v for k, v in loadmat(fh).items() if not k.startswith("__")}

    return read_npz(path, str(path), mmap=False)


def main(argv: list[str] | None = None) -> None:
    """``nirspi-convert IN -o OUT.npz --patterns KEY (--pos KEY --neg KEY | --interleaved KEY |
    --differential KEY | --measurements KEY)``."""
    p = argparse.ArgumentParser(prog="nirspi-convert", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("input", type=Path, help="an .npz or .mat file from another toolbox")
    p.add_argument("-o", "--output", type=Path, required=True, help="the recording to write (.npz)")
    p.add_argument("--patterns", required=True, metavar="KEY", help="the pattern rows or image stack")
    for key in ("pos", "neg", "interleaved", "differential", "measurements", "image", "timestamps"):
        p.add_argument(f"--{key}", metavar="KEY", help=f"input key holding {key}")
    p.add_argument("--flatten", choices=("C", "F"), default="C", help="F: patterns flattened column-major (MATLAB)")
    p.add_argument("--stack-last", action="store_true", help="patterns are an (n, n, m) stack (MATLAB)")
    p.add_argument("--gain", type=float, help="detector units per unit relative radiance per pixel")
    p.add_argument("--device", help="device name stored in the recording")
    p.add_argument("--compressed", action="store_true", help="write a compressed NPZ (slower to read)")
    ns = p.parse_args(argv)
    try:
        src = load_any(ns.input)
        keys = {
            k: getattr(ns, k)
            for k in ("patterns", "pos", "neg", "interleaved", "differential", "measurements", "image", "timestamps")
        }
        missing = [v for v in keys.values() if v is not None and v not in src]
        if missing:
            raise RecordingError(missing[0], f"not in {ns.input}; it has: {', '.join(sorted(src))}")
        arrays = {k: src[v] for k, v in keys.items() if v is not None}
        if ns.stack_last:
            if arrays["patterns"].ndim != 3:
                raise RecordingError("patterns", "--stack-last needs an (n, n, m) image stack")
            arrays["patterns"] = np.moveaxis(arrays["patterns"], -1, 0)
        out = convert(flatten=ns.flatten, gain=ns.gain, device=ns.device, **arrays)
        written = save_recording(ns.output, compressed=ns.compressed, **out)
    except (NirspiError, OSError, ValueError) as exc:
        print(f"nirspi-convert: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        raise SystemExit(2) from None
    form = "pattern spec (Hadamard)" if "indices" in out else "explicit patterns"
    print(f"nirspi-convert: wrote {written} ({len(out['measurements'])} readings, {form})")
