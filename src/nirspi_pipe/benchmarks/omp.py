"""``nirspi-bench omp``: OMP against the pre-issue-#15 OMP (reference) and numpy against OpenCL.

Every back end reconstructs the same acquisition (the camera image, zig-zag order, ``--ratio``
of the patterns, noise-free) with the same atom budget (the solver's defaults). The reference,
timed in the same run, is the OMP this package had before issue #15 (kept below, verbatim in
method): the correlation ``Mᵀ R M`` on the full ``n × n`` grid and classical Gram–Schmidt twice
(CGS2) over stored ``m``-vectors, ``O(m·k)`` per atom. The ratio ``numpy / reference`` is what to
read on a loaded machine; the issue measured the reference at 1.5 s for 128² at 25 % on a quiet
2-core machine, so ``ratio × 1.5 s`` estimates the quiet time. ``opencl / numpy`` below 1 means
OpenCL is faster. Images are compared (max difference, target ≤ 1e-5).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np
from scipy.linalg import solve_triangular

from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.omp import OMPSolver, basis_matrix, pick_atom
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera

T = TypeVar("T")

#: The reference's time for 128² at 25 % on a quiet 2-core machine (issue #15), seconds.
REFERENCE_QUIET_128_S = 1.5


def reference_omp(y: np.ndarray, n: int, indices: np.ndarray, k_max: int, tol: float = 1e-6) -> np.ndarray:
    """The pre-issue-#15 OMP (DCT basis, unnormalised selection): full-grid correlation, CGS2."""
    idx = np.asarray(indices, dtype=np.int64)
    rows, cols = idx // n, idx % n
    b = basis_matrix("dct", n)
    m_mat = np.ascontiguousarray(sylvester(n) @ b.T)
    m2 = m_mat * m_mat
    usable = np.sqrt(np.maximum((m2[rows].T @ m2[cols]).ravel(), 0.0)) > 0
    q_store = np.zeros((k_max, idx.size))
    r = y.astype(np.float64).copy()
    tri, qty, support, k = np.zeros((k_max, k_max)), np.zeros(k_max), [], 0
    ny = float(np.linalg.norm(y))
    while k < k_max:
        grid = np.zeros((n, n))
        grid[rows, cols] = r
        score = np.abs((m_mat.T @ grid @ m_mat).ravel())
        score[~usable] = -1.0
        p = pick_atom(score)
        if p < 0:
            break
        a_idx, b_idx = divmod(p, n)
        column = m_mat[rows, a_idx] * m_mat[cols, b_idx]
        qk = q_store[:k]
        c1 = qk @ column
        q = column - qk.T @ c1
        c2 = qk @ q
        q -= qk.T @ c2
        nq = float(np.linalg.norm(q))
        usable[p] = False
        if nq <= 1e-10 * float(np.linalg.norm(column)):
            continue
        q /= nq
        q_store[k] = q
        tri[:k, k], tri[k, k], qty[k] = c1 + c2, nq, float(q @ y)
        r -= float(q @ r) * q
        support.append(p)
        k += 1
        if float(np.linalg.norm(r)) <= tol * ny:
            break
    coeffs = np.zeros(n * n)
    if k:
        coeffs[np.asarray(support)] = solve_triangular(tri[:k, :k], qty[:k])
    return b.T @ coeffs.reshape(n, n) @ b


def _best_of(fn: Callable[[], T], repeat: int) -> tuple[float, T]:
    best, out = float("inf"), fn()
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench omp", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--ratio", type=float, default=0.25)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--opencl", action="store_true", help="also time the OpenCL back end")
    ns = parser.parse_args(argv)
    print(
        f"{'size':>6} {'atoms':>6} {'numpy ms':>9} {'ref ms':>9} {'np/ref':>7} {'quiet est s':>11} "
        f"{'opencl ms':>10} {'cl/np':>6} {'max diff':>9}"
    )
    for n in ns.sizes:
        scene = ImageTarget().render(Camera(resolution=n))
        acq = Simulator().acquire(scene, Zigzag(ns.ratio).select(n), n, np.random.default_rng(0))
        cpu = OMPSolver(backend="numpy")
        y = acq.coefficients()
        k_max = cpu.atoms(len(y))
        t_np, a = _best_of(lambda: cpu.solve(acq), ns.repeat)
        t_ref, ref = _best_of(lambda: reference_omp(y, n, acq.indices, k_max), ns.repeat)
        diff = float(np.max(np.abs(a.data - ref)))
        cl_ms, cl_ratio = "-", "-"
        if ns.opencl:
            ocl = OMPSolver(backend="opencl")  # builds the kernels here, outside the timing
            t_cl, b = _best_of(lambda: ocl.solve(acq), ns.repeat)
            diff = max(diff, float(np.max(np.abs(a.data - b.data))))
            cl_ms, cl_ratio = f"{t_cl * 1e3:.1f}", f"{t_cl / t_np:.2f}"
        quiet = f"{t_np / t_ref * REFERENCE_QUIET_128_S:.2f}" if n == 128 else "-"
        print(
            f"{n:>4}^2 {a.info['iterations']:>6} {t_np * 1e3:>9.1f} {t_ref * 1e3:>9.1f} "
            f"{t_np / t_ref:>7.3f} {quiet:>11} {cl_ms:>10} {cl_ratio:>6} {diff:>9.1e}"
        )
    return 0
