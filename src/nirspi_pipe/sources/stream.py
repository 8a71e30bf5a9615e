"""Source ``stream``: a live acquisition over TCP (protocol ``nirspi-stream/1``, docs/device.md).

The source sends the scan's pattern indices to the device, which displays them in that order
and streams one frame per ±1 pattern back. ``nirspi-device-emulator`` speaks the device side.
"""

from __future__ import annotations

import ipaddress
import socket
import struct
import time
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.device.protocol import (
    END_MARKER,
    FRAME_DTYPE,
    PROTOCOL,
    Channel,
    StreamError,
    read_exact,
    read_json_line,
    write_json_line,
)
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.safeio import check_budget, max_safe_reading, sanitize_text, short_repr
from nirspi_pipe.types import Acquisition, Scene

__all__ = ["Stream", "receive_acquisition"]


def _header_int(header: dict[str, Any], key: str, where: str) -> int:
    if key not in header:
        raise StreamError(key, "missing from the header", where)
    v = header[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise StreamError(key, f"expected an integer, got {short_repr(v)}", where)
    return v


def _check_header(header: dict[str, Any], indices: np.ndarray, n: int, where: str) -> tuple[int, Any]:
    """The header against the request: no error, the protocol, the size, the frame count and
    size, and a gain > 0; returns the count and the gain."""
    if "error" in header:
        raise StreamError("error", f"device refused the request: {sanitize_text(header['error'])}", where)
    if header.get("protocol") != PROTOCOL:
        raise StreamError("protocol", f"expected {PROTOCOL!r}, got {short_repr(header.get('protocol'))}", where)
    if _header_int(header, "n", where) != n:
        raise StreamError("n", f"device answers for {header['n']}x{header['n']}, requested {n}x{n}", where)
    count = _header_int(header, "count", where)
    if count != len(indices):
        raise StreamError("count", f"device announces {count} frames, {len(indices)} were requested", where)
    if _header_int(header, "frame_bytes", where) != FRAME_DTYPE.itemsize:
        raise StreamError(
            "frame_bytes", f"{header['frame_bytes']} != {FRAME_DTYPE.itemsize} (protocol mismatch)", where
        )
    gain = header.get("gain", 1.0)
    if isinstance(gain, bool) or not isinstance(gain, (int, float)) or not np.isfinite(gain) or gain <= 0:
        raise StreamError("gain", f"expected a number > 0, got {short_repr(gain)}", where)
    return count, gain


def _check_order(frames: np.ndarray, indices: np.ndarray, count: int, where: str) -> None:
    """The frames in sequence, each the pattern requested at its place."""
    seq = frames["seq"].astype(np.int64)
    bad = np.flatnonzero(seq != np.arange(count))
    if bad.size:
        raise StreamError("seq", f"frame {bad[0]} has seq {seq[bad[0]]} (frames lost or reordered)", where)
    bad = np.flatnonzero(frames["index"] != indices)
    if bad.size:
        raise StreamError(
            "index", f"frame {bad[0]} measured pattern {frames['index'][bad[0]]}, requested {indices[bad[0]]}", where
        )


def _check_values(
    frames: np.ndarray, readings: tuple[tuple[str, np.ndarray], ...], size: tuple[int, int, Any], where: str
) -> None:
    """The readings and timestamps finite, the timestamps not decreasing, and every reading
    small enough that the reconstruction stays finite (``size``: count, n and gain)."""
    count, n, gain = size
    for name, arr in (*readings[:1], ("t_s", frames["t_s"]), *readings[1:]):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise StreamError(name, f"{bad.size} non-finite value(s), first in frame {bad[0]}", where)
    back = np.flatnonzero(np.diff(frames["t_s"]) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise StreamError(
            "t_s",
            f"timestamps must not decrease (as in recorded files): frame {i} at "
            f"{frames['t_s'][i]:g} s after frame {i - 1} at {frames['t_s'][i - 1]:g} s",
            where,
        )
    limit = max_safe_reading(count, n * n)
    for name, arr in readings:
        peak = float(np.max(np.abs(arr))) / float(gain) if count else 0.0
        if not peak <= limit:
            raise StreamError(
                name,
                f"|reading| / gain reaches {peak:.3g}; the reconstruction would overflow "
                f"float64 (at most {limit:.3g} for {count} readings of {n}x{n})",
                where,
            )


def _check_end(fh: Any, count: int, where: str) -> None:
    """The end marker, counting the frames received."""
    end = read_exact(fh, len(END_MARKER) + 4, "end", where)
    if end[:4] != END_MARKER:
        raise StreamError("end", f"expected the end marker {END_MARKER!r}, got {end[:4]!r}", where)
    (sent,) = struct.unpack("<I", end[4:])
    if sent != count:
        raise StreamError("end", f"end marker counts {sent} frames, {count} received", where)


def receive_acquisition(fh: Any, indices: np.ndarray, n: int, where: str) -> Acquisition:
    """Read a header, the frames and the end marker from ``fh`` (after the request was sent)
    and check each against the request. Raises :class:`StreamError` naming the field."""
    header = read_json_line(fh, "header", where)
    count, gain = _check_header(header, indices, n, where)
    check_budget(count * FRAME_DTYPE.itemsize, f"{count} frames", where)
    raw = read_exact(fh, count * FRAME_DTYPE.itemsize, "frames", where)
    frames = np.frombuffer(raw, dtype=FRAME_DTYPE)
    _check_order(frames, indices, count, where)
    y_pos = frames["y_pos"].astype(np.float64)
    y_neg = frames["y_neg"].astype(np.float64)
    differential = bool(count) and bool(np.all(np.isnan(y_neg)))
    readings = (("y_pos", y_pos),) + (() if differential else (("y_neg", y_neg),))
    _check_values(frames, readings, (count, n, gain), where)
    _check_end(fh, count, where)
    return Acquisition(
        n=n,
        indices=np.asarray(indices, dtype=np.int64),
        y_pos=y_pos,
        y_neg=None if differential else y_neg,
        gain=float(gain),
        truth=None,
        timestamps_s=frames["t_s"].astype(np.float64),
        derived={},
        info={
            "device": sanitize_text(header.get("device", "?"), 100),
            "units": sanitize_text(header.get("units", ""), 40),
            "frames": int(count),
            "bytes": int(len(raw)),
            "differential": differential,
        },
    )


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address written as such (``127.0.0.0/8``, ``::1``) or
    ``localhost``; names are not resolved (a name is loopback only when it is ``localhost``)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class Stream:
    """Source ``stream``: measure the scan's patterns with a device over TCP.

    Attributes:
        host: device address: a loopback address (``127.0.0.1``, any of ``127.0.0.0/8``,
            ``::1``, ``localhost``; the emulator listens on 127.0.0.1) unless ``allow_remote``.
        allow_remote: connect to a host that is not loopback (a device on the network);
            false by default, so a config from someone else cannot make a run connect out.
        port: TCP port of the device (1–65535).
        timeout_s: total seconds for one acquisition (connect, request, header, every frame and
            the end marker); a device that has not finished by then fails with field
            ``frames`` (or the part it was sending). A total, not a per-read, deadline: a
            device trickling bytes cannot hold the run.
    """

    host: str = "127.0.0.1"
    port: int | None = None  # required: null (the shipped default) is refused below, so no declared range
    timeout_s: Annotated[float, Range(0.0, None, "seconds", lo_open=True)] = 10.0
    allow_remote: bool = False

    needs_scene = False

    def __post_init__(self) -> None:
        if not isinstance(self.allow_remote, bool):
            raise ConfigError("allow_remote", self.allow_remote, "true or false")
        if (
            not isinstance(self.host, str)
            or not self.host
            or len(self.host) > 253
            or any(ord(c) <= 32 or ord(c) == 127 for c in self.host)
        ):
            raise ConfigError("host", self.host, "a host name or IP address")
        if not self.allow_remote and not is_loopback(self.host):
            raise ConfigError(
                "host",
                self.host,
                "a loopback address (127.0.0.1, ::1, localhost); a device on the network needs source.allow_remote=true",
            )
        if (
            self.port is None
            or isinstance(self.port, bool)
            or not isinstance(self.port, int)
            or not 1 <= self.port <= 65535
        ):
            raise ConfigError("port", self.port, "a TCP port 1-65535 (source.port=PORT)")
        check_ranges(self)

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition:
        """Send the pattern ``indices`` and receive one frame per pattern (``scene``, ``rng`` unused)."""
        where = f"stream {self.host}:{self.port} (timeout_s={self.timeout_s:g})"
        idx = np.ascontiguousarray(indices, dtype="<i8")
        deadline = time.monotonic() + float(self.timeout_s)
        port = self.port
        assert port is not None  # refused by __post_init__
        try:
            sock = socket.create_connection((self.host, port), timeout=self.timeout_s)
        except TimeoutError:
            raise StreamError("connect", f"no answer within {self.timeout_s:g} s (source.timeout_s)", where) from None
        except OSError as exc:
            raise StreamError("connect", f"cannot connect ({exc.strerror or exc})", where) from None
        with sock:
            fh = Channel(sock, deadline)
            try:
                write_json_line(fh, {"protocol": PROTOCOL, "n": int(n), "count": int(idx.size)})  # type: ignore[arg-type]
                fh.write(idx.tobytes())
            except TimeoutError:
                raise StreamError(
                    "request", f"not sent within {self.timeout_s:g} s (source.timeout_s)", where
                ) from None
            except OSError as exc:
                raise StreamError("request", f"sending failed ({exc})", where) from None
            return receive_acquisition(fh, idx.astype(np.int64), n, where)
