"""``nirspi-device-emulator``: a single-pixel camera on loopback speaking ``nirspi-stream/1``.

It renders a nirspi-pipe scene (any ``scene=`` option, plugins included), measures the
requested Hadamard patterns in the split convention (noise-free readings from
:func:`~nirspi_pipe.physics.splitmeasure.split_measure`, plus a constant background on both halves
and optional Gaussian detector noise) and streams them back frame by frame.

It listens on 127.0.0.1 only, serves at most ``--connections`` acquisitions, and stops by
itself after ``--lifetime-s`` seconds in any case, slow clients included: every connection has
one total deadline (``io_timeout_s`` after it is accepted, and never past the lifetime), so an
idle or trickling client is dropped. Only connections that sent a complete request count as
served. A malformed request gets an ``{"error": ...}`` line, never a crash. ``--fault`` injects protocol errors
(truncated stream, NaN reading, stalled device, garbled header, wrong sequence) for tests.
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np

from nirspi_pipe.device.protocol import (
    FRAME_DTYPE,
    PROTOCOL,
    Channel,
    StreamError,
    encode_end,
    parse_json_line,
    read_exact,
    read_line,
    write_json_line,
)
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.splitmeasure import split_measure
from nirspi_pipe.safeio import sanitize_text, short_repr
from nirspi_pipe.types import Camera

__all__ = ["FAULTS", "Emulator", "main"]

FAULTS = ("none", "truncate", "nan", "stall", "bad-header", "seq", "no-end")
LOOPBACK = "127.0.0.1"


@dataclass
class Emulator:
    """The device side of ``nirspi-stream/1`` for one rendered scene.

    Attributes:
        radiance: ``(n, n)`` relative radiance of the scene.
        gain: detector units per unit relative radiance per pixel.
        background: reading added to both halves of every pattern (ambient light), detector units.
        noise_rel: Gaussian noise per reading relative to the mean half-pattern reading.
        pattern_rate_hz: patterns per second (timestamps; the emulator does not wait).
        seed: seed of the noise generator (one stream per connection, in order).
        differential: send ``y_pos − y_neg`` in ``y_pos`` and NaN in ``y_neg`` (a device that
            subtracts the halves itself).
        fault: one of :data:`FAULTS`.
        io_timeout_s: total seconds one connection may take from accept to the end marker
            (an idle client is dropped after this; the lifetime cuts it shorter).
        device: name sent in the header.
    """

    radiance: np.ndarray
    gain: float = 1.0
    background: float = 0.0
    noise_rel: float = 0.0
    pattern_rate_hz: float = 1000.0
    seed: int = 0
    differential: bool = False
    fault: str = "none"
    io_timeout_s: float = 10.0
    device: str = "nirspi-device-emulator"

    def __post_init__(self) -> None:
        if self.fault not in FAULTS:
            raise ValueError(f"fault must be one of {FAULTS}, got {self.fault!r}")
        self._sock: socket.socket | None = None
        self._seeds = np.random.SeedSequence(self.seed)

    @property
    def n(self) -> int:
        return int(self.radiance.shape[0])

    def bind(self, port: int = 0) -> int:
        """Listen on 127.0.0.1:``port`` (0 = a free port); returns the port."""
        self._sock = socket.create_server((LOOPBACK, port))
        return int(self._sock.getsockname()[1])

    def serve(self, connections: int = 1, lifetime_s: float = 60.0) -> int:
        """Serve up to ``connections`` acquisitions, stopping after ``lifetime_s`` in any case.
        Returns the number served (connections that sent a complete request; idle ones do not
        count). Call :meth:`bind` first."""
        if self._sock is None:
            self.bind()
        assert self._sock is not None
        deadline = time.monotonic() + lifetime_s
        served = 0
        with self._sock:
            while served < connections:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._sock.settimeout(min(left, 1.0))
                try:
                    conn, _ = self._sock.accept()
                except TimeoutError:
                    continue
                with conn:
                    fh = Channel(conn, min(deadline, time.monotonic() + self.io_timeout_s))
                    rng = np.random.default_rng(self._seeds.spawn(1)[0])
                    try:
                        if self.handle(fh, rng):  # type: ignore[arg-type]
                            served += 1
                    except (OSError, StreamError):
                        pass  # the client went away, stalled or broke the protocol: next connection
                    except Exception as exc:  # noqa: BLE001 - a bad request never stops the device
                        print(f"nirspi-device-emulator: request failed: {sanitize_text(exc)}", file=sys.stderr)
        return served

    def serve_in_thread(self, connections: int = 1, lifetime_s: float = 60.0) -> tuple[int, threading.Thread]:
        """Bind a free port and serve from a daemon thread; returns ``(port, thread)``."""
        port = self.bind(0)
        thread = threading.Thread(target=self.serve, args=(connections, lifetime_s), daemon=True)
        thread.start()
        return port, thread

    def readings(self, indices: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``(y_pos, y_neg)`` detector readings of the split patterns ``indices``."""
        y_pos, y_neg = split_measure(self.radiance, indices)
        sigma = self.noise_rel * 0.5 * float(self.radiance.sum())
        y_pos = self.gain * y_pos + self.background
        y_neg = self.gain * y_neg + self.background
        if sigma > 0:
            y_pos = y_pos + rng.normal(0.0, self.gain * sigma, y_pos.shape)
            y_neg = y_neg + rng.normal(0.0, self.gain * sigma, y_neg.shape)
        return y_pos, y_neg

    def handle(self, fh: BinaryIO, rng: np.random.Generator) -> bool:
        """One acquisition: read the request, send the header, the frames and the end marker.
        Returns True once a complete request was read (it then counts as served)."""
        raw = read_line(fh, "request")  # a timeout or a closed connection: not served
        try:
            req = parse_json_line(raw, "request")
        except StreamError as exc:
            write_json_line(fh, {"error": str(exc)})
            fh.flush()
            return True
        # untrusted JSON values, checked below before any use
        n: Any = req.get("n")
        count: Any = req.get("count")
        problem = None
        if req.get("protocol") != PROTOCOL:
            problem = f"protocol must be {PROTOCOL!r}, got {short_repr(req.get('protocol'), 40)}"
        elif isinstance(n, bool) or not isinstance(n, int) or n != self.n:
            problem = f"this device has {self.n}x{self.n} patterns, not {short_repr(n, 40)}"
        elif isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= self.n * self.n:
            problem = f"count must be an integer in [1, {self.n * self.n}], got {short_repr(count, 40)}"
        if problem is not None:
            write_json_line(fh, {"error": problem})
            fh.flush()
            return True
        indices = np.frombuffer(read_exact(fh, 8 * count, "indices"), dtype="<i8").astype(np.int64)
        if indices.min() < 0 or indices.max() >= self.n * self.n:
            write_json_line(fh, {"error": f"indices must lie in [0, {self.n * self.n})"})
            fh.flush()
            return True
        y_pos, y_neg = self.readings(indices, rng)
        frames = np.zeros(count, dtype=FRAME_DTYPE)
        frames["seq"] = np.arange(count)
        frames["index"] = indices
        frames["t_s"] = np.arange(count) * (2.0 / self.pattern_rate_hz)
        frames["y_pos"], frames["y_neg"] = y_pos, y_neg
        if self.differential:
            frames["y_pos"], frames["y_neg"] = y_pos - y_neg, np.nan
        header: dict[str, Any] = {
            "protocol": PROTOCOL,
            "n": self.n,
            "count": count,
            "frame_bytes": FRAME_DTYPE.itemsize,
            "gain": self.gain,
            "units": "relative",
            "device": self.device,
        }
        if self.fault == "bad-header":
            fh.write(b'{"protocol": "nirspi-stream/1", "n": \n')
            fh.flush()
            return True
        if self.fault == "nan":
            frames["y_pos"][count // 2] = np.nan
        if self.fault == "seq" and count > 2:
            frames["seq"][[1, 2]] = frames["seq"][[2, 1]]
        write_json_line(fh, header)
        payload = frames.tobytes()
        if self.fault == "truncate":
            fh.write(payload[: len(payload) // 2])
            fh.flush()
            return True
        if self.fault == "stall":
            fh.write(payload[: len(payload) // 2])
            fh.flush()
            wake = getattr(fh, "deadline", time.monotonic() + self.io_timeout_s)
            time.sleep(max(0.0, min(self.io_timeout_s, wake - time.monotonic())))
            return True
        fh.write(payload)
        if self.fault != "no-end":
            fh.write(encode_end(count))
        fh.flush()
        return True


def _check_arguments(ns: argparse.Namespace) -> str | None:
    """The first argument out of range, as one line naming it and the allowed values, or None."""
    if not 0 <= ns.port <= 65535:
        return f"--port={ns.port} is not allowed; allowed: a TCP port from 0 (a free one) to 65535"
    try:
        Camera(resolution=ns.resolution)  # the camera's own rule: a power of two from 2 to 4096
    except ConfigError as exc:
        return f"--resolution={ns.resolution} is not allowed; allowed: {exc.allowed}"
    if not (math.isfinite(ns.gain) and ns.gain > 0):
        return f"--gain={ns.gain} is not allowed; allowed: a finite number > 0 (what source=stream accepts)"
    if not math.isfinite(ns.background):
        return f"--background={ns.background} is not allowed; allowed: a finite number"
    if not (math.isfinite(ns.noise_rel) and ns.noise_rel >= 0):
        return f"--noise-rel={ns.noise_rel} is not allowed; allowed: a finite number >= 0 (0: no noise)"
    if ns.seed < 0:
        return f"--seed={ns.seed} is not allowed; allowed: an integer >= 0"
    if not 1 <= ns.connections <= 1000:
        return f"--connections={ns.connections} is not allowed; allowed: an integer from 1 to 1000"
    if not (math.isfinite(ns.lifetime_s) and 0 < ns.lifetime_s <= 3600):
        return f"--lifetime-s={ns.lifetime_s} is not allowed; allowed: seconds in (0, 3600]"
    return None


def _cause_line(exc: BaseException) -> str:
    """The error's first line, and the first line of its cause when the error wraps one (Hydra's
    ``Error in call to target …:`` says the cause on the next line)."""

    def first(e: BaseException) -> str:
        lines = str(e).strip().splitlines()
        return lines[0].strip() if lines else type(e).__name__

    cause = exc.__cause__
    if isinstance(cause, ConfigError):  # name the full key (scene.distance_mm) Hydra was building
        full = [ln.split(":", 1)[1].strip() for ln in str(exc).splitlines() if ln.startswith("full_key:")]
        return str(cause.under(full[0]) if full else cause)
    return first(exc) if cause is None else f"{first(exc).rstrip(':')}: {first(cause)}"


def main(
    argv: list[str] | None = None, render_scene: Callable[[str, int, list[str]], np.ndarray] | None = None
) -> None:
    """``nirspi-device-emulator``: serve a simulated scene on 127.0.0.1 (prints the port).

    ``render_scene(scene, resolution, overrides)`` renders a scene option's relative radiance;
    the console script (:func:`nirspi_pipe.app.devicecli.main`) passes the config layer's
    :func:`nirspi_pipe.app.configs.render_scene`, so this module composes no config itself."""
    p = argparse.ArgumentParser(prog="nirspi-device-emulator", description=__doc__.split("\n\n")[0])
    p.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: a free one; printed)")
    p.add_argument("--scene", default="sphere", help="a nirspi-pipe scene option (default sphere)")
    p.add_argument("--resolution", type=int, default=64, help="pixels per side (power of two)")
    p.add_argument(
        "--scene-override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra Hydra override for the scene, e.g. scene.distance_mm=300",
    )
    p.add_argument("--gain", type=float, default=1.0)
    p.add_argument("--background", type=float, default=0.0, help="constant reading added to both halves")
    p.add_argument("--noise-rel", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--differential", action="store_true", help="send pos − neg, NaN for neg")
    p.add_argument("--connections", type=int, default=1, help="acquisitions to serve before exiting")
    p.add_argument("--lifetime-s", type=float, default=60.0, help="exit after this many seconds anyway")
    p.add_argument("--fault", choices=FAULTS, default="none", help="inject a protocol error (tests)")
    ns = p.parse_args(argv)
    problem = _check_arguments(ns)
    if problem:
        print(f"nirspi-device-emulator: error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    if render_scene is None:
        print(
            "nirspi-device-emulator: error: no scene renderer; run the nirspi-device-emulator command", file=sys.stderr
        )
        raise SystemExit(2)
    try:
        radiance = render_scene(ns.scene, ns.resolution, ns.scene_override)
    except Exception as exc:  # noqa: BLE001 - one line for the user
        print(f"nirspi-device-emulator: error: {_cause_line(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
    emu = Emulator(
        radiance,
        gain=ns.gain,
        background=ns.background,
        noise_rel=ns.noise_rel,
        seed=ns.seed,
        differential=ns.differential,
        fault=ns.fault,
    )
    port = emu.bind(ns.port)
    print(json.dumps({"host": LOOPBACK, "port": port, "n": emu.n, "scene": ns.scene}), flush=True)
    served = emu.serve(ns.connections, ns.lifetime_s)
    print(f"nirspi-device-emulator: served {served} acquisition(s), exiting", file=sys.stderr)
