"""OpenCL back end of the OMP solver (pyopencl, float64; runs on PoCL's CPU device here).

Kernels: the correlation ``G = Mᵀ R M`` (scatter of the residual on the Hadamard grid, then
two ``n × n`` products, one work item per output entry), and the classical Gram–Schmidt pair
``c = Q a`` / ``q = a − Qᵀ c`` over the stored orthonormal columns. All in double precision,
which the device must support (``cl_khr_fp64``), so that it agrees with the numpy reference to
``1e-5``. The host code in :mod:`nirspi_pipe.solvers.omp` picks atoms and solves the final
triangular system for both back ends.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError

__all__ = ["OpenCLOmpBackend", "opencl_context"]

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

/* c[j] = sum_i Q[j, i] v[i]   (Q row-major: k_max x m; one work item per stored vector) */
__kernel void q_dot(__global const double *Q, __global const double *v, __global double *c,
                    const int m) {
    const int j = get_global_id(0);
    double s = 0.0;
    for (int i = 0; i < m; ++i) s += Q[(long)j * m + i] * v[i];
    c[j] = s;
}

/* v[i] -= sum_{j<k} c[j] Q[j, i]   (one work item per measurement) */
__kernel void q_sub(__global const double *Q, __global const double *c, __global double *v,
                    const int m, const int k) {
    const int i = get_global_id(0);
    double s = v[i];
    for (int j = 0; j < k; ++j) s -= c[j] * Q[(long)j * m + i];
    v[i] = s;
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
        kernels = {k: cl.Kernel(program, k) for k in ("scatter", "mt_r", "t_m", "q_dot", "q_sub")}
        return ctx, cl.CommandQueue(ctx), kernels
    raise NirspiError(
        "solver.backend=opencl: no OpenCL device could build the kernels ("
        + "; ".join(failures)
        + "). The pip PoCL (LLVM 14) does not know recent CPUs; Debian's pocl-opencl-icd does"
    )


class OpenCLOmpBackend:
    """OMP's correlation and Gram–Schmidt steps on an OpenCL device (see module doc)."""

    def __init__(self, m_mat: np.ndarray, rows: np.ndarray, cols: np.ndarray, k_max: int) -> None:
        import pyopencl as cl

        self.cl = cl
        self.ctx, self.queue, kernels = opencl_context()
        self.n = int(m_mat.shape[0])
        self.m_count = int(rows.size)
        mf = cl.mem_flags
        n2 = self.n * self.n
        self.k_scatter = kernels["scatter"]
        self.k_mt_r = kernels["mt_r"]
        self.k_t_m = kernels["t_m"]
        self.k_dot = kernels["q_dot"]
        self.k_sub = kernels["q_sub"]
        self.d_m = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(m_mat, np.float64))
        self.d_rows = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rows.astype(np.int32))
        self.d_cols = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=cols.astype(np.int32))
        self.d_resid = cl.Buffer(self.ctx, mf.READ_ONLY, size=8 * self.m_count)
        self.d_grid = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * n2)
        self.d_tmp = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * n2)
        self.d_g = cl.Buffer(self.ctx, mf.WRITE_ONLY, size=8 * n2)
        self.d_q = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * max(1, k_max) * self.m_count)
        self.d_v = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * self.m_count)
        self.d_c = cl.Buffer(self.ctx, mf.READ_WRITE, size=8 * max(1, k_max))
        self.h_g = np.empty(n2)

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        cl, q, n = self.cl, self.queue, np.int32(self.n)
        cl.enqueue_copy(q, self.d_resid, np.ascontiguousarray(residual, np.float64))
        cl.enqueue_fill_buffer(q, self.d_grid, np.float64(0.0), 0, 8 * self.n * self.n)
        self.k_scatter(q, (self.m_count,), None, self.d_grid, self.d_rows, self.d_cols, self.d_resid, n)
        self.k_mt_r(q, (self.n, self.n), None, self.d_m, self.d_grid, self.d_tmp, n)
        self.k_t_m(q, (self.n, self.n), None, self.d_tmp, self.d_m, self.d_g, n)
        cl.enqueue_copy(q, self.h_g, self.d_g)
        return self.h_g.copy()

    def orthogonalize(self, column: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k == 0:
            return column.copy(), np.zeros(0)
        cl, q, m = self.cl, self.queue, np.int32(self.m_count)
        cl.enqueue_copy(q, self.d_v, np.ascontiguousarray(column, np.float64))
        total = np.zeros(k)
        part = np.empty(k)
        for _ in range(2):  # CGS2: classical Gram–Schmidt, twice
            self.k_dot(q, (k,), None, self.d_q, self.d_v, self.d_c, m)
            self.k_sub(q, (self.m_count,), None, self.d_q, self.d_c, self.d_v, m, np.int32(k))
            cl.enqueue_copy(q, part, self.d_c)
            total += part
        out = np.empty(self.m_count)
        cl.enqueue_copy(q, out, self.d_v)
        return out, total

    def store(self, vec: np.ndarray, k: int) -> None:
        self.cl.enqueue_copy(
            self.queue, self.d_q, np.ascontiguousarray(vec, np.float64), dst_offset=8 * k * self.m_count
        )
