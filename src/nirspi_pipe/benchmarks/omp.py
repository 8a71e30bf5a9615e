"""``nirspi-bench omp``: OMP with the numpy back end against the OpenCL one, same problem.

Both reconstruct the same acquisition (zig-zag order, ``--ratio`` of the patterns, the sphere
scene) with the same atom budget; the ratio ``opencl / numpy`` below 1 means OpenCL is faster.
Also reports the largest difference between the two images (target ≤ 1e-5).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.solvers.omp import OMPSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera


def _best_of(fn, repeat: int) -> tuple[float, object]:  # type: ignore[no-untyped-def]
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench omp", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64])
    parser.add_argument("--ratio", type=float, default=0.25)
    parser.add_argument("--basis", default="dct")
    parser.add_argument("--repeat", type=int, default=3)
    ns = parser.parse_args(argv)
    print(f"{'size':>6} {'atoms':>6} {'numpy ms':>10} {'opencl ms':>10} {'ratio':>7} {'max diff':>9}")
    for n in ns.sizes:
        scene = Sphere().render(Camera(resolution=n))
        acq = Simulator().acquire(scene, Zigzag(ns.ratio).select(n), n, np.random.default_rng(0))
        cpu, ocl = OMPSolver(basis=ns.basis), OMPSolver(basis=ns.basis, backend="opencl")
        ocl.solve(acq)  # warm-up: OpenCL context and kernel build
        t_np, a = _best_of(lambda: cpu.solve(acq), ns.repeat)
        t_cl, b = _best_of(lambda: ocl.solve(acq), ns.repeat)
        diff = float(np.max(np.abs(a.data - b.data)))  # type: ignore[union-attr]
        print(f"{n:>4}^2 {a.info['iterations']:>6} {t_np * 1e3:>10.1f} {t_cl * 1e3:>10.1f} "  # type: ignore[union-attr]
              f"{t_cl / t_np:>7.2f} {diff:>9.1e}")
    return 0
