"""``nirspi-bench recorded``: a recorded file of explicit split Hadamard patterns, read through
the fast path (recognise the patterns, then ``fwht``) against a dense least-squares solve of the
same explicit matrix (what a general solver does without recognition), in the same process.

The file is the one the issue describes: ``n × n`` (default 64), all ``2·n²`` split patterns as
an explicit float matrix (8,192 × 4,096 at 64), in sequency order, interleaved ±, with ambient
light on every reading. Target: fast path < 1 s at 64 × 64. The ratio dense / fast is printed.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from nirspi_pipe.device.recording import load_recording, save_recording
from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.recorded import recording_to_acquisition
from nirspi_pipe.types import Camera


def split_hadamard_file(path: Path, n: int, dtype: str = "float64") -> np.ndarray:
    """Write the benchmark recording; returns the ground-truth image."""
    img = Sphere().render(Camera(n)).radiance
    h = sylvester(n)
    rank = np.argsort((np.diff(h, axis=1) != 0).sum(axis=1))  # sequency order of the rows
    k = (rank[:, None] * n + rank[None, :]).ravel()
    pm = (h[k // n][:, :, None] * h[k % n][:, None, :]).reshape(n * n, n * n)
    pats = np.empty((2 * n * n, n * n), dtype=dtype)
    pats[0::2], pats[1::2] = (1 + pm) / 2, (1 - pm) / 2
    y = pats.astype(np.float64) @ img.ravel() + 0.37
    save_recording(path, measurements=y, patterns=pats, image=img)
    return img


def fast_path(path: Path) -> tuple[np.ndarray, dict]:
    """Load, recognise and solve (what ``source=recorded solver=fwht`` does)."""
    acq = recording_to_acquisition(load_recording(path))
    return FWHTSolver().solve(acq).data, dict(acq.info)


def dense_lstsq(path: Path) -> np.ndarray:
    """Least squares on the explicit matrix with an offset column (ambient light)."""
    rec = load_recording(path)
    a = np.column_stack([np.asarray(rec.patterns, dtype=np.float64), np.ones(rec.measurements.size)])
    sol = np.linalg.lstsq(a, rec.measurements, rcond=None)[0]
    return sol[:-1].reshape(rec.n, rec.n)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench recorded", description=__doc__)
    parser.add_argument("--n", type=int, default=64, help="resolution (power of two)")
    parser.add_argument("--repeat", type=int, default=5, help="fast-path repetitions (median)")
    parser.add_argument(
        "--dense-n",
        type=int,
        default=32,
        help="resolution of the dense reference (64 takes minutes; its time scales ~N³)",
    )
    ns = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "split.npz"
        img = split_hadamard_file(path, ns.n)
        times: list[float] = []
        info: dict[str, object] = {}
        for _ in range(ns.repeat):
            t0 = time.perf_counter()
            rec, info = fast_path(path)
            times.append(time.perf_counter() - t0)
        t_fast = float(np.median(times))
        err = float(np.abs(rec - img).max())
        print(
            f"fast path {ns.n}x{ns.n}: {2 * ns.n**2} explicit patterns, median {t_fast:.3f} s "
            f"(min {min(times):.3f}), max error {err:.2e}, fast_path={info.get('fast_path')}"
        )
        dpath = Path(tmp) / "dense.npz"
        dimg = split_hadamard_file(dpath, ns.dense_n)
        t0 = time.perf_counter()
        d_fast, _ = fast_path(dpath)
        t_fast_d = time.perf_counter() - t0
        t0 = time.perf_counter()
        dense = dense_lstsq(dpath)
        t_dense = time.perf_counter() - t0
        print(
            f"at {ns.dense_n}x{ns.dense_n}: dense lstsq {t_dense:.3f} s, fast path {t_fast_d:.4f} s, "
            f"ratio dense/fast {t_dense / t_fast_d:.0f}; max errors {np.abs(dense - dimg).max():.1e} / "
            f"{np.abs(d_fast - dimg).max():.1e}"
        )
    ok = t_fast < 1.0 and err < 1e-9
    print("target (< 1 s, exact):", "met" if ok else "NOT met")
    return 0 if ok else 1
