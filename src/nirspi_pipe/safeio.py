"""Bounded readers for files and streams from outside (docs/hostile.md).

Every reader here checks what a file *declares* (array shapes, element counts, member sizes)
against the file's real length and against a memory budget **before** it allocates, and reads
compressed data through a bounded stream, so a 300-byte header that announces 10⁹ vertices or a
9 MB zip bomb gives a one-line :class:`UnsafeInputError` naming the file instead of exhausting
memory. The helpers are pure functions of their arguments (the budget is an argument; its
default comes from :data:`DEFAULT_BUDGET_BYTES` or the ``NIRSPI_READ_BUDGET_MB`` environment
variable, read at call time).
"""

from __future__ import annotations

import ast
import math
import os
import re
import stat
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nirspi_pipe.errors import NirspiError

__all__ = [
    "DEFAULT_BUDGET_BYTES",
    "MAX_DEFLATE_RATIO",
    "UnsafeInputError",
    "check_budget",
    "json_depth",
    "max_safe_reading",
    "read_budget",
    "read_npz",
    "sanitize_text",
    "short_repr",
]

#: Assumed: 1 GiB, four times the largest input the docs describe (a 64×64 recording with 8,192
#: explicit float64 split patterns, 268 MB, docs/device.md), and well below a laptop's RAM.
DEFAULT_BUDGET_BYTES = 1 << 30

#: zlib's technical notes: deflate cannot compress by more than 1032:1, so a member that declares
#: a larger ratio lies about its size (np.savez writes deflate or stored members only).
MAX_DEFLATE_RATIO = 1032

_CHUNK = 1 << 18  # numpy.format's read size; 1 MiB chunks measured ~1.5x slower (nirspi-bench readers)
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069]")


class UnsafeInputError(NirspiError, ValueError):
    """A file or stream declares more than it holds, or more than the memory budget allows."""


def open_regular(path: str | Path, where: str | None = None) -> Any:
    """``path`` opened for binary reading when it is a regular file; :class:`UnsafeInputError`
    (one line naming it) for a FIFO, a device, a socket or a folder (``FileNotFoundError``, as
    raised, when there is nothing), without blocking: it is
    opened with ``O_NONBLOCK`` (a FIFO with no writer would block a plain ``open``), checked with
    ``fstat`` + ``S_ISREG`` on the open descriptor (no swap between check and read), and only
    then switched back to blocking reads."""
    where = where or str(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise  # as it is: callers tell a missing file (a job not run) from a bad one
    except OSError as exc:
        raise UnsafeInputError(f"{where}: cannot open ({exc.strerror or exc})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = "a FIFO" if stat.S_ISFIFO(mode) else "a folder" if stat.S_ISDIR(mode) else "a device or socket"
            raise UnsafeInputError(f"{where}: {kind}, not a regular file; allowed: a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: str | Path, limit: int, where: str | None = None) -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`), its size checked against
    ``limit`` bytes before reading, and at most ``limit`` bytes read (a file growing meanwhile
    is refused too); :class:`UnsafeInputError` otherwise."""
    where = where or str(path)
    with open_regular(path, where) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > limit:
            raise UnsafeInputError(f"{where}: {_fmt_bytes(size)}, more than the {_fmt_bytes(limit)} allowed here")
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise UnsafeInputError(f"{where}: more than the {_fmt_bytes(limit)} allowed here")
    return bytes(data)


def read_budget(budget: int | None = None) -> int:
    """The memory budget in bytes: ``budget`` if given, else ``NIRSPI_READ_BUDGET_MB`` (MiB),
    else :data:`DEFAULT_BUDGET_BYTES`."""
    if budget is not None:
        return int(budget)
    env = os.environ.get("NIRSPI_READ_BUDGET_MB", "").strip()
    if env:
        try:
            mb = float(env)
        except ValueError:
            raise UnsafeInputError(
                f"NIRSPI_READ_BUDGET_MB={env!r} is not allowed; allowed: a number of MiB > 0"
            ) from None
        if not (math.isfinite(mb) and mb > 0):
            raise UnsafeInputError(f"NIRSPI_READ_BUDGET_MB={env!r} is not allowed; allowed: a number of MiB > 0")
        return int(mb * (1 << 20))
    return DEFAULT_BUDGET_BYTES


def _fmt_bytes(n: int) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n} bytes"


def check_budget(nbytes: int, what: str, where: str, budget: int | None = None) -> None:
    """Raise :class:`UnsafeInputError` when allocating ``nbytes`` for ``what`` exceeds the budget."""
    limit = read_budget(budget)
    if nbytes > limit:
        raise UnsafeInputError(
            f"{where}: {what} needs {_fmt_bytes(nbytes)}, over the read budget of {_fmt_bytes(limit)} "
            "(set NIRSPI_READ_BUDGET_MB to allow more)"
        )


def sanitize_text(text: object, limit: int = 200) -> str:
    """``text`` as one printable line: control characters (ANSI escapes, newlines, bidi
    overrides) become ``?``, and it is cut to ``limit`` characters."""
    s = _CONTROL.sub("?", str(text))
    return s if len(s) <= limit else s[: limit - 1] + "…"


def short_repr(value: object, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters (repr escapes control characters)."""
    r = repr(value)
    return r if len(r) <= limit else r[: limit - 1] + "…"


def json_depth(raw: bytes) -> int:
    """Maximum nesting depth of ``[``/``{`` in a JSON text, strings skipped (no parsing)."""
    depth = best = 0
    in_str = escaped = False
    for ch in raw.decode("utf-8", errors="replace"):
        if in_str:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            best = max(best, depth)
        elif ch in "]}":
            depth -= 1
    return best


def max_safe_reading(n_readings: int, n_pixels: int) -> float:
    """Largest ``|reading| / gain`` whose images and metrics stay finite in float64.

    A solver sums up to ``n_readings`` readings per pixel and metrics square and sum the
    ``n_pixels`` values, so ``(|y|/gain · n_readings)² · n_pixels`` must stay below the largest
    float64: ``|y|/gain ≤ sqrt(max / n_pixels) / n_readings``. A physical relative radiance gives
    ``|y|/gain ≤ n_pixels``, far below this bound (2.6e148 for 8,192 readings of 64×64).
    """
    big = float(np.finfo(np.float64).max)
    return math.sqrt(big / max(1, n_pixels)) / max(1, n_readings)


# ---------------------------------------------------------------------------------------------
# NPZ


def _npy_header_text(fh: Any, key: str, where: str) -> tuple[bytes, int]:
    """The raw header dict text of a ``.npy`` stream and the header's full length in bytes
    (magic, length field and text), read with bounded reads."""
    magic = fh.read(8)
    if len(magic) != 8 or magic[:6] != b"\x93NUMPY":
        raise UnsafeInputError(f"{where}: key '{key}': not a .npy array (bad magic)")
    major = magic[6]
    if major == 1:
        hlen_bytes, fmt = fh.read(2), "<H"
    elif major in (2, 3):
        hlen_bytes, fmt = fh.read(4), "<I"
    else:
        raise UnsafeInputError(f"{where}: key '{key}': unsupported .npy version {major}")
    if len(hlen_bytes) != struct.calcsize(fmt):
        raise UnsafeInputError(f"{where}: key '{key}': truncated .npy header")
    (hlen,) = struct.unpack(fmt, hlen_bytes)
    if hlen > 65536:  # numpy's own limit is 10,000 bytes (max_header_size)
        raise UnsafeInputError(f"{where}: key '{key}': .npy header of {hlen} bytes (at most 65536)")
    text = fh.read(hlen)
    if len(text) != hlen:
        raise UnsafeInputError(f"{where}: key '{key}': truncated .npy header")
    return text, 8 + len(hlen_bytes) + hlen


def _npy_header_dict(text: bytes, key: str, where: str) -> dict:
    """The header's dict, parsed as a literal: exactly descr, fortran_order and shape."""
    try:
        d = ast.literal_eval(text.decode("latin1"))
    except (ValueError, SyntaxError, MemoryError, RecursionError, TypeError):
        raise UnsafeInputError(f"{where}: key '{key}': unreadable .npy header") from None
    if not isinstance(d, dict) or set(d) != {"descr", "fortran_order", "shape"}:
        raise UnsafeInputError(f"{where}: key '{key}': .npy header must have descr, fortran_order and shape")
    return d


def _npy_dtype(descr: Any, key: str, where: str) -> np.dtype:
    """The header's dtype: a plain number or string dtype, never one holding Python objects."""
    try:
        dtype = np.lib.format.descr_to_dtype(descr)
    except (TypeError, ValueError):
        raise UnsafeInputError(f"{where}: key '{key}': dtype {short_repr(descr)} is not a numpy dtype") from None
    if dtype.hasobject:
        raise UnsafeInputError(
            f"{where}: key '{key}': holds pickled Python objects, which are never loaded (store numbers or strings)"
        )
    if dtype.fields is not None or dtype.subdtype is not None or dtype.itemsize == 0:
        raise UnsafeInputError(f"{where}: key '{key}': dtype {dtype} is not a plain number or string dtype")
    return dtype


def _is_shape(shape: Any) -> bool:
    """A tuple of at most 32 integers >= 0 (bools are not integers here)."""
    return (
        isinstance(shape, tuple)
        and len(shape) <= 32
        and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
    )


def _npy_header(fh: Any, key: str, where: str) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Parse a ``.npy`` header from a file-like ``fh`` with bounded reads (never allocates more
    than the header) and check it: non-negative integer shape, a plain non-object dtype."""
    text, length = _npy_header_text(fh, key, where)
    d = _npy_header_dict(text, key, where)
    shape = d["shape"]
    if not _is_shape(shape):
        raise UnsafeInputError(f"{where}: key '{key}': shape {short_repr(shape)} is not a tuple of integers >= 0")
    if not isinstance(d["fortran_order"], bool):
        raise UnsafeInputError(f"{where}: key '{key}': fortran_order must be True or False")
    dtype = _npy_dtype(d["descr"], key, where)
    return shape, d["fortran_order"], dtype, length


def _readinto(fh: Any, buf: np.ndarray, key: str, where: str) -> None:
    """Fill the uint8 array ``buf`` from ``fh`` in bounded chunks (truncation names the key)."""
    got = 0
    while got < buf.size:
        chunk = fh.read(min(_CHUNK, buf.size - got))
        if not chunk:
            raise UnsafeInputError(f"{where}: key '{key}': truncated data ({got} of {buf.size} bytes)")
        buf[got : got + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
        got += len(chunk)


def read_npz(
    path: str | Path, where: str | None = None, budget: int | None = None, mmap: bool = True
) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz``, read within a memory budget, never unpickling.

    Checks, before anything is allocated: the file is a zip whose members are ``.npy`` files,
    stored or deflated (the two ``np.savez`` writes); each member's declared size against the
    budget (all members together, too), its compression ratio against deflate's 1032:1 ceiling,
    a stored member's extent against the file's length, and the array header's shape × itemsize
    against the member's declared size. Data is read through zipfile's bounded stream (it never
    yields more than the declared size, and checks the CRC). With ``mmap``, uncompressed
    members are memory-mapped read-only instead of copied.

    Raises :class:`UnsafeInputError` (one line, naming the file and the key) on any problem.
    """
    path = Path(path)
    where = where or f"{path}"
    limit = read_budget(budget)
    try:
        fh = open_regular(path, where)  # a regular file (never a FIFO or device); closed by `with fh` below
    except FileNotFoundError:
        raise UnsafeInputError(f"{where}: file does not exist") from None
    file_len = os.fstat(fh.fileno()).st_size
    out: dict[str, np.ndarray] = {}
    with fh:
        head = fh.read(6)
        fh.seek(0)
        if head == b"\x93NUMPY":
            raise UnsafeInputError(f"{where}: a single .npy array, not an NPZ archive of named arrays")
        try:
            zf = zipfile.ZipFile(fh)
        except (
            zipfile.BadZipFile,
            OSError,
            ValueError,
            EOFError,
            NotImplementedError,
        ) as exc:  # e.g. 'zip file version 6.4'
            raise UnsafeInputError(
                f"{where}: not a readable NPZ file ({type(exc).__name__}: {sanitize_text(exc, 120)})"
            ) from None
        with zf:
            infos = zf.infolist()
            if len(infos) > 4096:
                raise UnsafeInputError(f"{where}: {len(infos)} members (an NPZ of at most 4096 arrays is read)")
            for info in infos:  # declared sizes first: nothing is decompressed yet
                check_budget(
                    info.file_size, f"key '{sanitize_text(info.filename.removesuffix('.npy'), 60)}'", where, limit
                )
            total = sum(max(0, i.file_size) for i in infos)
            if total > limit:
                big = max(infos, key=lambda i: i.file_size).filename.removesuffix(".npy")
                check_budget(total, f"all members together (largest: key '{sanitize_text(big, 60)}')", where, limit)
            for info in infos:
                name = info.filename
                key = name.removesuffix(".npy")
                skey = sanitize_text(key, 60)
                if not name.endswith(".npy") or info.is_dir():
                    raise UnsafeInputError(f"{where}: member '{skey}' is not a .npy array")
                if key in out:
                    raise UnsafeInputError(f"{where}: key '{skey}' appears twice")
                if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                    raise UnsafeInputError(
                        f"{where}: key '{skey}': compression method {info.compress_type} is not allowed; "
                        "allowed: stored or deflate (numpy.savez / savez_compressed)"
                    )
                if info.flag_bits & 0x1:
                    raise UnsafeInputError(f"{where}: key '{skey}': encrypted members are not read")
                if (
                    info.compress_type == zipfile.ZIP_DEFLATED
                    and info.file_size > MAX_DEFLATE_RATIO * max(info.compress_size, 1) + 1024
                ):
                    raise UnsafeInputError(
                        f"{where}: key '{skey}': declares {info.file_size} bytes from {info.compress_size} compressed "
                        f"(more than deflate's {MAX_DEFLATE_RATIO}:1; corrupt or a zip bomb)"
                    )
                if info.compress_size > file_len or info.header_offset + info.compress_size > file_len:
                    raise UnsafeInputError(
                        f"{where}: key '{skey}': declares {info.compress_size} bytes of data, the file has {file_len}"
                    )
                check_budget(info.file_size, f"key '{skey}'", where, limit)
                out[key] = _read_member(path, zf, info, skey, where, file_len, mmap)
    return out


def _read_member(
    path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, key: str, where: str, file_len: int, mmap: bool
) -> np.ndarray:
    try:
        with zf.open(info) as member:
            shape, fortran, dtype, header_len = _npy_header(member, key, where)
            nbytes = math.prod(shape) * dtype.itemsize
            if header_len + nbytes != info.file_size:
                raise UnsafeInputError(
                    f"{where}: key '{key}': header declares shape {short_repr(shape)} of {dtype} ({nbytes} bytes), "
                    f"the member holds {info.file_size - header_len}"
                )
            order: Literal["C", "F"] = "F" if fortran else "C"
            if mmap and info.compress_type == zipfile.ZIP_STORED and nbytes > 0:
                start = _stored_data_offset(path, info, key, where)
                offset = start + header_len
                if offset + nbytes > file_len:
                    raise UnsafeInputError(f"{where}: key '{key}': data runs past the end of the file")
                # the CRC is not checked for mapped members (that would read them whole)
                return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order=order)
            buf = np.empty(nbytes, dtype=np.uint8)
            _readinto(member, buf, key, where)
            if member.read(1):
                raise UnsafeInputError(f"{where}: key '{key}': more data than the header declares")
            return buf.view(dtype).reshape(shape, order=order)
    except UnsafeInputError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as exc:
        raise UnsafeInputError(
            f"{where}: key '{key}': truncated or corrupt data ({type(exc).__name__}: {sanitize_text(exc, 120)})"
        ) from None


def _stored_data_offset(path: Path, info: zipfile.ZipInfo, key: str, where: str) -> int:
    """Offset of a stored member's data (after its local header) in the file."""
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)
    if len(local) < 30 or local[:4] != b"PK\x03\x04":
        raise UnsafeInputError(f"{where}: key '{key}': corrupt local header")
    name_len = int.from_bytes(local[26:28], "little")
    extra_len = int.from_bytes(local[28:30], "little")
    return info.header_offset + 30 + name_len + extra_len
