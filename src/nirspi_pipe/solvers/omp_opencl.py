"""OpenCL back end of the OMP solver (pyopencl, float64; runs on PoCL's CPU device here).

Kernels: the correlation ``G = Mᵀ R M`` (scatter of the residual on the Hadamard grid, then
two ``n × n`` products, one work item per output entry) and the synthesis ``M S Mᵀ`` (the same
two product kernels on ``Mᵀ``). All in double precision, which the device must support
(``cl_khr_fp64``), so that it agrees with the numpy reference to ``1e-5``. The host code in
:mod:`nirspi_pipe.solvers.omp` picks atoms and keeps the Cholesky factor for both back ends.

The program is built once per process (:func:`opencl_context`, called by ``OMPSolver`` when it
is constructed, so compilation is never part of a solve's time) and pyopencl keeps the built
binary in its on-disk cache (``~/.cache/pyopencl``), so later processes skip the compiler.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError

__all__ = ["OpenCLOmpBackend", "opencl_context", "gpu_available"]

_SOURCE = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

__kernel void scatter(__global double *R, __global const int *rows, __global const int *cols,
                      __global const double *r, const int n) {
    const int k = get_global_id(0);
    R[rows[k] * n + cols[k]] = r[k];
}

/* T = M^T R : T[a, j] = sum_i M[i, a] R[i, j] */
__kernel void mt_r(__global const double *M, __global const double *R, __global double *T,
                   const int n) {
    const int a = get_global_id(0), j = get_global_id(1);
    double s = 0.0;
    for (int i = 0; i < n; ++i) s += M[i * n + a] * R[i * n + j];
    T[a * n + j] = s;
}

/* G = T M : G[a, b] = sum_j T[a, j] M[j, b] */
__kernel void t_m(__global const double *T, __global const double *M, __global double *G,
                  const int n) {
    const int a = get_global_id(0), b = get_global_id(1);
    double s = 0.0;
    for (int j = 0; j < n; ++j) s += T[a * n + j] * M[j * n + b];
    G[a * n + b] = s;
}

"""


@lru_cache(maxsize=1)
def opencl_context() -> tuple[Any, Any, dict[str, Any]]:
    """``(context, queue, kernels by name)`` on the first OpenCL device with float64 whose compiler
    builds the kernels; built once per process. Raises :class:`NirspiError` naming each
    device's failure when none can."""
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise NirspiError(f"solver.backend=opencl needs pyopencl ({exc})") from None
    devices = []
    try:
        for platform in cl.get_platforms():
            devices += [d for d in platform.get_devices() if "cl_khr_fp64" in d.extensions]
    except cl.Error as exc:
        raise NirspiError(f"solver.backend=opencl: no OpenCL platform ({exc}); install pyopencl[pocl]") from None
    if not devices:
        raise NirspiError("solver.backend=opencl: no OpenCL device with float64 (cl_khr_fp64)")
    failures = []
    for device in devices:  # the first device whose compiler builds the kernels
        ctx = cl.Context([device])
        try:
            program = cl.Program(ctx, _SOURCE).build()
        except cl.Error as exc:
            log = str(exc).strip().splitlines()
            failures.append(f"{device.platform.version} / {device.name}: {log[-3] if len(log) >= 3 else log[-1]}")
            continue
        kernels = {k: cl.Kernel(program, k) for k in ("scatter", "mt_r", "t_m")}
        return ctx, cl.CommandQueue(ctx), kernels
    raise NirspiError(
        "solver.backend=opencl: no OpenCL device could build the kernels ("
        + "; ".join(failures)
        + "). The pip PoCL (LLVM 14) does not know recent CPUs; Debian's pocl-opencl-icd does"
    )


@lru_cache(maxsize=1)
def gpu_available() -> bool:
    """True when the device :func:`opencl_context` picks is a GPU (cached per process)."""
    try:
        import pyopencl as cl

        ctx, _, _ = opencl_context()
    except Exception:  # noqa: BLE001 - no working device means "no"
        return False
    return any(d.type & cl.device_type.GPU for d in ctx.devices)


class OpenCLOmpBackend:
    """OMP's correlation and synthesis on an OpenCL device (see module doc)."""

    def __init__(self, m_mat: np.ndarray, rows: np.ndarray, cols: np.ndarray, k_max: int) -> None:
        import pyopencl as cl

        self.cl = cl
        self.ctx, self.queue, kernels = opencl_context()
        self.n = int(m_mat.shape[0])
        self.m_count = int(rows.size)
        self.rows, self.cols = rows, cols
        self.m_host = m_mat
        mf = cl.mem_flags
        n2 = self.n * self.n
        self.k_scatter = kernels["scatter"]
        self.k_mt_r = kernels["mt_r"]
        self.k_t_m = kernels["t_m"]
        self.d_m = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(m_mat, np.float64))
        self.d_mt = cl.Buffer(
            self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(m_mat.T, np.float64)
        )
        self.d_rows = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rows.astype(np.int32))
        self.d_cols = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=cols.astype(np.int32))
        self.d_resid = cl.Buffer(self.ctx, mf.READ_ONLY, size=8 * self.m_count)
        self.d_grid = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * n2)
        self.d_tmp = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * n2)
        self.d_g = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * n2)
        self.h_g = np.empty(n2)

    def _products(self, left, right) -> np.ndarray:
        """``leftᵀ · grid · right`` on the device (``left``/``right`` buffers of ``M`` or ``Mᵀ``)."""
        cl, q, n = self.cl, self.queue, np.int32(self.n)
        self.k_mt_r(q, (self.n, self.n), None, left, self.d_grid, self.d_tmp, n)
        self.k_t_m(q, (self.n, self.n), None, self.d_tmp, right, self.d_g, n)
        cl.enqueue_copy(q, self.h_g, self.d_g)
        return self.h_g.copy()

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        cl, q, n = self.cl, self.queue, np.int32(self.n)
        cl.enqueue_copy(q, self.d_resid, np.ascontiguousarray(residual, np.float64))
        cl.enqueue_fill_buffer(q, self.d_grid, np.float64(0.0), 0, 8 * self.n * self.n)
        self.k_scatter(q, (self.m_count,), None, self.d_grid, self.d_rows, self.d_cols, self.d_resid, n)
        return self._products(self.d_m, self.d_m)

    def gram(self, p: int, support: np.ndarray) -> np.ndarray:
        a_idx, b_idx = divmod(p, self.n)
        column = self.m_host[self.rows, a_idx] * self.m_host[self.cols, b_idx]
        return self.correlate(column)[support]

    def project(self, support: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``Aᵀ A_S u``: one full synthesis and one correlation on the device."""
        coeffs = np.zeros(self.n * self.n)
        coeffs[support] = u
        return self.correlate(self.synthesize(coeffs))

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        self.cl.enqueue_copy(self.queue, self.d_grid, np.ascontiguousarray(coeffs, np.float64))
        full = self._products(self.d_mt, self.d_mt).reshape(self.n, self.n)  # (M S) Mᵀ
        return full[self.rows, self.cols]
