"""The ``nirspi-stream/1`` protocol: single-pixel readings over TCP (docs/device.md).

One acquisition per connection; all binary numbers little-endian.

1. **Request** (client → device): a JSON line (UTF-8, ``\\n``-terminated, at most 64 KiB)
   ``{"protocol": "nirspi-stream/1", "n": 64, "count": m}``, then ``m`` int64 flat pattern
   indices (``k = i·n + j``, natural Sylvester rows, see :mod:`nirspi_pipe.patterns.hadamard`)
   in the order they are to be displayed.
2. **Header** (device → client): a JSON line ``{"protocol": "nirspi-stream/1", "n": 64,
   "count": m, "frame_bytes": 36, "gain": 1.0, "units": "V", "device": "…"}``, or
   ``{"error": "…"}`` when the device refuses the request.
3. **Frames**: ``count`` records of 36 bytes, one per ±1 pattern, in display order:
   ``seq`` uint32 (0, 1, …), ``index`` int64 (the requested pattern), ``t_s`` float64 (seconds
   since the start), ``y_pos`` float64, ``y_neg`` float64 (the readings of the positive and
   negative half-patterns, detector units; a device measuring the difference directly sends it
   in ``y_pos`` and NaN in ``y_neg``, for every frame).
4. **End marker**: the 4 bytes ``NEND`` and the uint32 frame count.

Anything else (a short read, a closed connection, a frame out of sequence, a non-finite
reading, a missing end marker) is an error naming the field.
"""

from __future__ import annotations

import json
import socket
import struct
import time
from typing import Any, BinaryIO

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.safeio import json_depth, sanitize_text

__all__ = [
    "PROTOCOL",
    "FRAME_DTYPE",
    "END_MARKER",
    "MAX_LINE",
    "MAX_DEPTH",
    "StreamError",
    "Channel",
    "read_line",
    "read_json_line",
    "parse_json_line",
    "read_exact",
    "write_json_line",
    "encode_end",
]

PROTOCOL = "nirspi-stream/1"
FRAME_DTYPE = np.dtype([("seq", "<u4"), ("index", "<i8"), ("t_s", "<f8"), ("y_pos", "<f8"), ("y_neg", "<f8")])
assert FRAME_DTYPE.itemsize == 36
END_MARKER = b"NEND"
MAX_LINE = 64 * 1024
#: Assumed: the protocol's request and header are flat JSON objects (depth 1); 8 leaves room for
#: nested extensions while keeping the parser far from Python's recursion limit.
MAX_DEPTH = 8


class StreamError(NirspiError):
    """A stream broke the protocol; the message names the field."""

    def __init__(self, field: str, problem: str, where: str = "") -> None:
        self.field = field
        prefix = f"{where}: " if where else ""
        super().__init__(f"{prefix}stream field '{field}': {sanitize_text(problem, 300)}")


class Channel:
    """A connected socket whose reads and writes all share one **total** deadline.

    Every ``recv``/``sendall`` gets the time left until ``deadline`` (``time.monotonic()``
    seconds) as its timeout, so a peer trickling one byte at a time cannot hold the connection
    past the deadline (a per-read timeout would be reset by every byte). Past the deadline each
    call raises ``socket.timeout``. ``read``/``readline``/``write``/``flush`` make it a drop-in
    for the binary file object of ``socket.makefile``.
    """

    def __init__(self, sock: socket.socket, deadline: float) -> None:
        self.sock = sock
        self.deadline = deadline
        self._buf = bytearray()

    def _arm(self) -> None:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("deadline passed")
        self.sock.settimeout(left)

    def _recv(self, size: int) -> bytes:
        self._arm()
        return self.sock.recv(max(1, min(size, 1 << 20)))

    def read(self, size: int) -> bytes:
        """Up to ``size`` bytes (at least one unless the peer closed): b"" at end of stream."""
        if self._buf:
            out = bytes(self._buf[:size])
            del self._buf[:size]
            return out
        return self._recv(size)

    def readline(self, limit: int) -> bytes:
        """Bytes up to and including ``\n``, at most ``limit`` bytes; fewer at end of stream."""
        while b"\n" not in self._buf and len(self._buf) < limit:
            chunk = self._recv(limit - len(self._buf))
            if not chunk:
                break
            self._buf += chunk
        cut = self._buf.find(b"\n")
        end = min(limit, cut + 1) if cut >= 0 else min(limit, len(self._buf))
        out = bytes(self._buf[:end])
        del self._buf[:end]
        return out

    def write(self, data: bytes) -> int:
        self._arm()
        self.sock.sendall(data)
        return len(data)

    def flush(self) -> None:
        """Writes are unbuffered."""


def read_exact(fh: BinaryIO | Channel, size: int, field: str, where: str = "") -> bytes:
    """Read exactly ``size`` bytes or raise :class:`StreamError` (truncated or too slow)."""
    buf = bytearray(size)
    got = 0
    while got < size:
        try:
            chunk = fh.read(size - got)
        except TimeoutError:
            raise StreamError(field, f"timed out after {got} of {size} bytes", where) from None
        except OSError as exc:
            raise StreamError(field, f"connection failed after {got} of {size} bytes ({exc})", where) from None
        if not chunk:
            raise StreamError(field, f"stream truncated: connection closed after {got} of {size} bytes", where)
        buf[got : got + len(chunk)] = chunk
        got += len(chunk)
    return bytes(buf)


def read_line(fh: BinaryIO | Channel, field: str, where: str = "") -> bytes:
    """One ``\n``-terminated line (at most :data:`MAX_LINE` bytes), without the newline."""
    try:
        line = fh.readline(MAX_LINE + 1)
    except TimeoutError:
        raise StreamError(field, "timed out waiting for the line", where) from None
    except OSError as exc:
        raise StreamError(field, f"connection failed ({exc})", where) from None
    if not line:
        raise StreamError(field, "stream truncated: connection closed before the line", where)
    if not line.endswith(b"\n"):
        if len(line) > MAX_LINE:
            raise StreamError(field, f"line longer than {MAX_LINE} bytes", where)
        raise StreamError(field, "stream truncated inside the line", where)
    return line[:-1]


def read_json_line(fh: BinaryIO | Channel, field: str, where: str = "") -> dict[str, Any]:
    """A JSON object on one line, nested at most :data:`MAX_DEPTH` deep."""
    return parse_json_line(read_line(fh, field, where), field, where)


def parse_json_line(raw: bytes, field: str, where: str = "") -> dict[str, Any]:
    """A JSON object from one line's bytes, nested at most :data:`MAX_DEPTH` deep."""
    depth = json_depth(raw)
    if depth > MAX_DEPTH:
        raise StreamError(field, f"JSON nested {depth} deep (at most {MAX_DEPTH})", where)
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise StreamError(field, f"not a JSON line ({type(exc).__name__}: {exc})", where) from None
    if not isinstance(obj, dict):
        raise StreamError(field, "not a JSON object", where)
    return obj


def write_json_line(fh: BinaryIO, obj: dict[str, Any]) -> None:
    """Write ``obj`` as one compact JSON line."""
    fh.write(json.dumps(obj, separators=(",", ":")).encode("utf-8") + b"\n")


def encode_end(count: int) -> bytes:
    """The end marker: ``NEND`` and the uint32 frame count."""
    return END_MARKER + struct.pack("<I", count)
