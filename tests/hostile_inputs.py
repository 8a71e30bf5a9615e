"""Hostile input generators for tests/test_hostile_*.py (everything built in code, no blobs).

Each generator writes one file into a folder and returns its path. The suite runs the loaders on
them, in a subprocess where a native library might crash (see :func:`run_isolated`).
"""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np

PLY_HEAD = (
    "ply\nformat {fmt} 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
    "element face {nf}\nproperty list uchar int vertex_indices\nend_header\n"
)


def tetra() -> tuple[np.ndarray, np.ndarray]:
    """A closed tetrahedron, outward faces."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32)
    return v, f


def ply_binary(v: np.ndarray, f: np.ndarray, nv: int | None = None, nf: int | None = None) -> bytes:
    head = PLY_HEAD.format(fmt="binary_little_endian", nv=len(v) if nv is None else nv, nf=len(f) if nf is None else nf)
    rows = b"".join(struct.pack("<B3i", 3, *map(int, tri)) for tri in f)
    return head.encode() + v.astype("<f4").tobytes() + rows


def ply_ascii(v: np.ndarray, f: np.ndarray) -> bytes:
    head = PLY_HEAD.format(fmt="ascii", nv=len(v), nf=len(f))
    body = "".join(f"{a:g} {b:g} {c:g}\n" for a, b, c in v) + "".join(f"3 {a} {b} {c}\n" for a, b, c in f)
    return (head + body).encode()


def stl_binary(v: np.ndarray, f: np.ndarray, declared: int | None = None) -> bytes:
    tri = v[f].astype("<f4")
    rows = b"".join(struct.pack("<3f", 0, 0, 0) + t.tobytes() + b"\0\0" for t in tri)
    return b"\0" * 80 + struct.pack("<I", len(f) if declared is None else declared) + rows


def obj_text(v: np.ndarray, f: np.ndarray) -> bytes:
    return (
        "".join(f"v {a:g} {b:g} {c:g}\n" for a, b, c in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    ).encode()


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def npz_bytes(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for name, data in members.items():
            zf.writestr(name if name.endswith(".npy") else name + ".npy", data)
    return buf.getvalue()


def recording_members(n: int = 4, scale: float = 1.0) -> dict[str, bytes]:
    """A small valid spec recording (stacked split of all n² Hadamard patterns)."""
    from nirspi_pipe.patterns.hadamard import sylvester

    rng = np.random.default_rng(0)
    img = rng.random((n, n))
    h = sylvester(n)
    pats = np.einsum("ia,jb->ijab", h, h).reshape(n * n, n * n)
    pos = (1 + pats) / 2 @ img.ravel()
    neg = (1 - pats) / 2 @ img.ravel()
    return {
        "measurements": npy_bytes(np.concatenate([pos, neg]) * scale),
        "basis": npy_bytes(np.array("hadamard")),
        "resolution": npy_bytes(np.array(n)),
        "split": npy_bytes(np.array("stacked")),
        "indices": npy_bytes(np.arange(n * n)),
        "image": npy_bytes(img),
    }


def set_central_sizes(data: bytes, name: str, file_size: int) -> bytes:
    """Rewrite the uncompressed size a zip's central directory declares for member ``name``."""
    raw = bytearray(data)
    at = raw.find(b"PK\x01\x02")
    while at >= 0:
        name_len = struct.unpack_from("<H", raw, at + 28)[0]
        if raw[at + 46 : at + 46 + name_len].decode() == name:
            struct.pack_into("<I", raw, at + 24, file_size)
        at = raw.find(b"PK\x01\x02", at + 4)
    return bytes(raw)


def png(width: int, height: int, idat: bytes | None = None) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    data = zlib.compress(b"\0" * 64) if idat is None else idat
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", data) + chunk(b"IEND", b"")


ISOLATED_RUNNER = r"""
import json, sys, warnings
warnings.simplefilter("ignore")
from nirspi_pipe.errors import NirspiError
kind, paths = sys.argv[1], sys.argv[2:]
def load(path):
    if kind == "mesh":
        from nirspi_pipe.scene.shapes import load_mesh
        return load_mesh(path)
    if kind == "image":
        from nirspi_pipe.scene.objects import load_gray_image
        return load_gray_image(path)
    if kind == "recording":
        from nirspi_pipe.device.recording import load_recording
        return load_recording(path)
    if kind == "weights":
        from nirspi_pipe.upscale.fsrcnn import load_weights
        return load_weights(2, path)
    raise SystemExit("unknown kind " + kind)
for path in paths:
    print(json.dumps({"path": path, "start": True}), flush=True)
    try:
        load(path)
        out = {"path": path, "result": "ok"}
    except NirspiError as exc:
        out = {"path": path, "result": "error", "message": str(exc)}
    except BaseException as exc:
        out = {"path": path, "result": "crash", "message": f"{type(exc).__name__}: {exc}"}
    print(json.dumps(out), flush=True)
"""


def run_isolated(kind: str, paths: list[Path], budget_mb: float | None = None, timeout: float = 120) -> list[dict]:
    """Load every file of ``paths`` with the ``kind`` loader in one child process (a segfault
    there fails the calling test instead of killing pytest); returns one dict per file:
    ``result`` is ``ok``, ``error`` (a one-line NirspiError) or ``crash`` (anything else)."""
    import os

    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if budget_mb is not None:
        env["NIRSPI_READ_BUDGET_MB"] = str(budget_mb)
    res = subprocess.run(
        [sys.executable, "-c", ISOLATED_RUNNER, kind, *map(str, paths)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
    lines = [json.loads(ln) for ln in res.stdout.splitlines() if ln.startswith("{")]
    done = [ln for ln in lines if "result" in ln]
    if res.returncode != 0 or len(done) != len(paths):
        started = [ln["path"] for ln in lines if "start" in ln]
        last = started[-1] if started else None
        raise AssertionError(f"loader process died (exit {res.returncode}) on {last}: {res.stderr[-2000:]}")
    return done
