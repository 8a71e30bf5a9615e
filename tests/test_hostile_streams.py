"""Hostile streams and clients (docs/hostile.md): the stream client against scripted devices,
the emulator against scripted clients. Everything binds to and connects to 127.0.0.1; every
loop is bounded in count and time."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.device.emulator import Emulator
from nirspi_pipe.device.protocol import FRAME_DTYPE, PROTOCOL, StreamError, encode_end
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.sources.stream import Stream

LOOPBACK = "127.0.0.1"
N = 4


def frames(count: int, t: np.ndarray | None = None, y: float = 1.0) -> bytes:
    fr = np.zeros(count, dtype=FRAME_DTYPE)
    fr["seq"] = np.arange(count)
    fr["index"] = np.arange(count)
    fr["t_s"] = np.arange(count) * 1e-3 if t is None else t
    fr["y_pos"], fr["y_neg"] = y, 0.5 * y
    return fr.tobytes()


def header(count: int, **extra: object) -> bytes:
    h = {"protocol": PROTOCOL, "n": N, "count": count, "frame_bytes": 36, "gain": 1.0, **extra}
    return json.dumps(h).encode() + b"\n"


class Device:
    """A scripted device on 127.0.0.1: reads one request, then sends ``reply`` in pieces of
    ``piece`` bytes, ``gap_s`` apart (a trickle when small), for at most ``max_s`` seconds."""

    def __init__(self, reply: bytes, piece: int = 1 << 20, gap_s: float = 0.0, max_s: float = 10.0) -> None:
        self.reply, self.piece, self.gap_s, self.max_s = reply, piece, gap_s, max_s
        self.sent = 0  # bytes of ``reply`` sent so far
        self.sock = socket.create_server((LOOPBACK, 0))
        self.port = self.sock.getsockname()[1]
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.sock.settimeout(self.max_s)
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        end = time.monotonic() + self.max_s
        with conn, self.sock:
            conn.settimeout(self.max_s)
            try:
                conn.recv(1 << 16)
                for i in range(0, len(self.reply), self.piece):
                    if time.monotonic() > end:
                        return
                    conn.sendall(self.reply[i : i + self.piece])
                    self.sent = i + len(self.reply[i : i + self.piece])
                    time.sleep(self.gap_s)
            except OSError:
                return


def acquire(port: int, count: int = N * N, timeout_s: float = 5.0):
    return Stream(port=port, timeout_s=timeout_s).acquire(None, np.arange(count), N, np.random.default_rng(0))


def test_a_good_scripted_device_is_accepted() -> None:
    dev = Device(header(16) + frames(16) + encode_end(16))
    acq = acquire(dev.port)
    assert acq.y_pos.size == 16 and np.all(acq.y_pos == 1.0)


def test_trickling_device_hits_the_total_deadline() -> None:
    # one byte every 20 ms: each read succeeds quickly, but the whole acquisition cannot. The
    # client gives up while the device is still sending (669 bytes: >= 13.4 s to trickle out).
    reply = header(16) + frames(16) + encode_end(16)
    dev = Device(reply, piece=1, gap_s=0.02, max_s=5)
    with pytest.raises(StreamError, match="timed out"):
        acquire(dev.port, timeout_s=0.6)
    assert 0 < dev.sent < len(reply)


@pytest.mark.parametrize(
    "name,reply,field",
    [
        ("nested header", b"[" * 5000 + b"]" * 5000 + b"\n", "header"),
        ("nested object", b'{"a":' * 20 + b"1" + b"}" * 20 + b"\n", "header"),
        (
            "decreasing timestamps",
            header(16) + frames(16, t=np.array([0.0, 1, 2, 3, 2.5] + list(range(4, 15)), float)) + encode_end(16),
            "t_s",
        ),
        ("1e308 readings", header(16) + frames(16, y=1e308) + encode_end(16), "y_pos"),
        ("tiny gain", header(16, gain=1e-300) + frames(16) + encode_end(16), "y_pos"),
        ("count as bool", header(16).replace(b'"count": 16', b'"count": true'), "count"),
        ("huge line", b"x" * 70000, "header"),
        ("wrong count", header(10**12) + frames(16), "count"),
    ],
)
def test_hostile_device_replies_name_the_field(name: str, reply: bytes, field: str) -> None:
    dev = Device(reply)
    with pytest.raises(StreamError) as err:
        acquire(dev.port)
    msg = str(err.value)
    assert f"field '{field}'" in msg and "\n" not in msg and f"{LOOPBACK}:{dev.port}" in msg, (name, msg)


def test_device_error_text_is_sanitised() -> None:
    evil = "\x1b[2J\x1b[31mpwned\x07\r\nsecond line\u202e" + "A" * 5000
    dev = Device(json.dumps({"error": evil}).encode() + b"\n")
    with pytest.raises(StreamError) as err:
        acquire(dev.port)
    msg = str(err.value)
    assert "pwned" in msg and "\x1b" not in msg and "\n" not in msg and "\r" not in msg and "\u202e" not in msg
    assert len(msg) < 600


def test_header_strings_are_sanitised_in_the_record() -> None:
    dev = Device(header(16, device="\x1b]0;title\x07dev", units="V\x1b[0m") + frames(16) + encode_end(16))
    acq = acquire(dev.port)
    assert "\x1b" not in acq.info["device"] and "\x07" not in acq.info["device"] and "\x1b" not in acq.info["units"]


# --------------------------------------------------------------------------- the emulator


def emulator(**kw: object) -> Emulator:
    return Emulator(np.full((N, N), 0.5), **kw)  # type: ignore[arg-type]


def talk(port: int, payload: bytes, read_s: float = 2.0) -> bytes:
    with socket.create_connection((LOOPBACK, port), timeout=read_s) as s:
        s.sendall(payload)
        s.shutdown(socket.SHUT_WR)
        out = b""
        end = time.monotonic() + read_s
        while time.monotonic() < end:
            try:
                chunk = s.recv(1 << 16)
            except (TimeoutError, OSError):
                break
            if not chunk:
                break
            out += chunk
        return out


BAD_REQUESTS = [
    b'{"protocol": "nirspi-stream/1", "n": 4, "count": true}\n',
    b'{"protocol": "nirspi-stream/1", "n": 4, "count": 1e9}\n',
    b'{"protocol": "nirspi-stream/1", "n": true, "count": 1}\n',
    b'{"protocol": "nirspi-stream/1", "n": [4], "count": 1}\n',
    b'{"protocol": "nirspi-stream/1", "n": 4, "count": -1}\n',
    b'{"protocol": {"x": 1}, "n": 4, "count": 1}\n',
    b"[" * 3000 + b"\n",
    b"\xff\xfe\n",
    b"null\n",
]


def test_emulator_answers_bad_requests_and_keeps_serving() -> None:
    emu = emulator(io_timeout_s=2.0)
    port, thread = emu.serve_in_thread(connections=len(BAD_REQUESTS) + 1, lifetime_s=30)
    for req in BAD_REQUESTS:
        out = talk(port, req)
        assert b'"error"' in out and out.endswith(b"\n") and out.count(b"\n") == 1, (req, out)
    acq = acquire(port, count=16)  # still alive and serving
    assert acq.y_pos.size == 16
    thread.join(timeout=5)
    assert not thread.is_alive()


def test_emulator_lifetime_holds_against_a_slow_client() -> None:
    emu = emulator(io_timeout_s=60.0)
    port, thread = emu.serve_in_thread(connections=5, lifetime_s=1.0)
    request = b'{"protocol": "nirspi-stream/1", "n": 4, "count": 16}'  # no newline: never finishes
    sent = 0
    with socket.create_connection((LOOPBACK, port), timeout=5) as s:
        for b in request:  # one byte every 0.1 s: 5.3 s, the io_timeout 60 s
            try:
                s.sendall(bytes([b]))
            except OSError:
                break
            sent += 1
            time.sleep(0.1)
            if not thread.is_alive():
                break
        thread.join(timeout=5)
    # the emulator stopped (its lifetime) while the client was still sending its request
    assert not thread.is_alive() and sent < len(request)


def test_emulator_drops_idle_clients_and_does_not_count_them() -> None:
    emu = emulator(io_timeout_s=0.3)
    result: list[int] = []
    port = emu.bind(0)
    thread = threading.Thread(target=lambda: result.append(emu.serve(connections=1, lifetime_s=20)), daemon=True)
    thread.start()
    with socket.create_connection((LOOPBACK, port), timeout=5) as idle:
        idle.settimeout(3)
        assert idle.recv(1) == b""  # closed by the emulator after io_timeout_s, having sent nothing
    assert thread.is_alive()  # the idle connection was not counted as served
    acquire(port, count=16)
    thread.join(timeout=5)
    assert result == [1]


def test_emulator_and_client_use_loopback_only() -> None:
    emu = emulator()
    port = emu.bind(0)
    assert emu._sock is not None and emu._sock.getsockname()[0] == LOOPBACK
    emu._sock.close()
    assert Stream.host == LOOPBACK and port > 0


@pytest.mark.parametrize("host", ["10.0.0.1", "192.168.1.20", "example.com", "0.0.0.0", "::", "127.0.0.1.evil.org"])
def test_the_client_refuses_a_remote_host_unless_allowed(host: str) -> None:
    """Loopback by default (issue 41): a host that is not loopback is refused naming
    ``host`` and the key that allows it, before any connection; ``allow_remote=true`` takes it."""
    with pytest.raises(ConfigError, match="source.allow_remote=true") as err:
        Stream(host=host, port=9)
    assert err.value.key == "host"
    assert Stream(host=host, port=9, allow_remote=True).host == host


@pytest.mark.parametrize("host", ["127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost", "LOCALHOST"])
def test_the_client_takes_loopback_hosts(host: str) -> None:
    assert Stream(host=host, port=9).host == host


@pytest.mark.parametrize(("host", "allow"), [("", False), ("a b", True), ("x\n", True), ("127.0.0.1", "yes")])
def test_bad_host_or_allow_remote_values_name_their_key(host: str, allow: object) -> None:
    with pytest.raises(ConfigError) as err:
        Stream(host=host, port=9, allow_remote=allow)  # type: ignore[arg-type]
    assert err.value.key in ("host", "allow_remote")


@settings(max_examples=40, deadline=None)
@given(
    req=st.one_of(
        st.binary(max_size=200).map(lambda b: b.replace(b"\n", b"") + b"\n"),
        st.dictionaries(
            st.sampled_from(["protocol", "n", "count", "x"]),
            st.one_of(
                st.none(),
                st.booleans(),
                st.integers(-(10**20), 10**20),
                st.floats(allow_nan=True),
                st.text(max_size=20),
                st.lists(st.integers(), max_size=3),
            ),
            max_size=4,
        ).map(lambda d: json.dumps(d).encode() + b"\n"),
    )
)
def test_fuzzed_requests_never_break_the_emulator(req: bytes) -> None:
    emu = emulator(io_timeout_s=0.5)
    fh_out = _Pipe(req + np.arange(16, dtype="<i8").tobytes())
    try:
        emu.handle(fh_out, np.random.default_rng(0))  # type: ignore[arg-type]
    except StreamError as exc:  # a broken line or missing indices: the connection is dropped
        assert "\n" not in str(exc)
    if fh_out.written:
        first = fh_out.written.split(b"\n", 1)[0]
        assert isinstance(json.loads(first), dict)


class _Pipe:
    """An in-memory stand-in for the connection (``read``/``readline``/``write``/``flush``)."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos, self.written = data, 0, b""

    def read(self, size: int) -> bytes:
        out = self.data[self.pos : self.pos + size]
        self.pos += len(out)
        return out

    def readline(self, limit: int) -> bytes:
        end = self.data.find(b"\n", self.pos)
        stop = min(self.pos + limit, len(self.data) if end < 0 else end + 1)
        out = self.data[self.pos : stop]
        self.pos = stop
        return out

    def write(self, data: bytes) -> int:
        self.written += data
        return len(data)

    def flush(self) -> None:
        pass
