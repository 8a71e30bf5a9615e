"""OpenCL back end of the OMP solver (pyopencl, float64): the whole solve stays on the device.

The algorithm is :func:`nirspi_pipe.solvers.omp.omp_core`'s, step for step (the same selection
rule with its tie window, the same inverse Cholesky factor ``L⁻¹`` of the support's Gram matrix,
the same residual norm ``‖y‖² − ‖z‖²`` for the stopping test), in six kernels per atom, all of
them on the device and none of them read back:

1. ``pick``: ``score = |g| · weight``, its maximum and the lowest index within
   :data:`~nirspi_pipe.solvers.omp.TIE_RTOL` of it (one work-group per problem);
2. ``gram``: ``c = A_Sᵀ a_p``, one work-group per support atom, the atoms' columns made on the
   fly from ``M`` (``A[t, (a, b)] = M[i_t, a] M[j_t, b]``);
3. ``tri``: ``w = L⁻¹ c``, ``d² = ‖a_p‖² − ‖w‖²``, the new row ``[−wᵀL⁻¹, 1]/d`` of ``L⁻¹``,
   ``z_k``, the coefficients ``s = L⁻ᵀ z`` and the stopping test (one work-group per problem);
4. ``synth``: ``q_k = A_S (row k of L⁻¹)`` at the measured cells, scattered on the Hadamard grid;
5. ``mtr`` and 6. ``tm_upd``: ``g ← g − z_k Mᵀ Q M``, the correlation update (two ``n × n``
   products).

A kernel of a problem that has stopped returns at once, so the host enqueues iterations without
looking: in chunks of 32, 128, 512, ... atoms, with one read of the problems' state between
chunks (to stop early when ``tol`` is met), and one read of the support and coefficients at the
end. ``L⁻¹`` is kept twice, by rows and by columns, so that both triangular products read memory
in order. Independent problems with the same patterns (tiles, the images of a sweep) are a batch:
each kernel's last global dimension is the problem.

Everything is float64, which the device must support (``cl_khr_fp64``); sums run in another order
than numpy's BLAS, so images differ by rounding (parity bound 1e-10, tests/test_parity.py).
The program is built once per process and device (:func:`opencl_context`, called by ``OMPSolver``
when it is constructed, so compilation is never part of a solve's time); pyopencl keeps the
binary in its on-disk cache. The kernels' OpenCL C source is :mod:`nirspi_pipe.solvers.omp_kernels`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.opencl_devices import is_gpu
from nirspi_pipe.opencl_devices import opencl_context as accel_context
from nirspi_pipe.solvers.omp_kernels import KERNELS, kernel_source

__all__ = ["DeviceOmp", "opencl_context", "gpu_available", "STOP_REASONS"]

#: Stop codes of the device state, by index (0: still running).
STOP_REASONS = ("running", "max_atoms", "exhausted", "residual_tol", "zero_measurements")


@lru_cache(maxsize=4)
def opencl_context(device: str = "auto") -> tuple[Any, Any, dict[str, Any]]:
    """``(context, queue, kernels by name)`` on the device ``device`` names
    (:func:`nirspi_pipe.opencl_devices.opencl_device`), built once per process. Raises
    :class:`NirspiError` (one line) when there is none or its compiler fails."""
    try:
        import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise NirspiError(f"solver.backend=opencl needs pyopencl ({exc})") from None

    try:
        ctx, queue = accel_context(device)
    except NirspiError as exc:
        raise NirspiError(f"solver.backend=opencl: {exc}") from None
    except cl.Error as exc:
        raise NirspiError(f"solver.backend=opencl: no OpenCL platform ({exc}); install pyopencl[pocl]") from None
    try:
        program = cl.Program(ctx, kernel_source()).build()
    except cl.Error as exc:
        log = str(exc).strip().splitlines()
        dev = ctx.devices[0]
        why = log[-3] if len(log) >= 3 else log[-1]
        raise NirspiError(
            f"solver.backend=opencl: {dev.platform.version} / {dev.name} could not build the OMP kernels ({why}). "
            "The pip PoCL (LLVM 14) does not know recent CPUs; Debian's pocl-opencl-icd does"
        ) from None
    return ctx, queue, {k: cl.Kernel(program, k) for k in KERNELS}


@lru_cache(maxsize=4)
def gpu_available(device: str = "auto") -> bool:
    """True when the device :func:`opencl_context` picks for ``device`` is a GPU (cached)."""
    try:
        ctx, _, _ = opencl_context(device)
    except Exception:  # noqa: BLE001 - no working device means "no"
        return False
    return is_gpu(ctx.devices[0])


#: How a device solve is laid out (:meth:`DeviceOmp.solve`).
MODES = ("kernels", "workgroup")

#: Largest image side solved in one work-group by default: per atom the work-group does
#: ``2n³ + 2·k·m`` multiply-adds (1.1 M at 64² and 256 atoms, 16 M at 128² and 1000), so at 64² the
#: one launch beats six launches per atom (each costs a few µs on a GPU) and at 128² one
#: work-group has too much to do. An estimate from operation counts, to be replaced by the
#: ``nirspi-bench gpu`` measurement of both modes (docs/gpu.md).
WORKGROUP_MAX_N = 64


def _pow2_at_most(x: int) -> int:
    return 1 << (max(1, int(x)).bit_length() - 1)


class DeviceOmp:
    """OMP for Hadamard measurements at fixed ``(rows, cols)`` cells, solved on the device.

    Args:
        m_mat: ``M = H Bᵀ`` (``n × n``).
        rows, cols: the measured Hadamard cells (``(m,)`` each).
        colnorm: ``‖A[:, p]‖`` (``(N,)``).
        k_max: atoms at most.
        device: a device spec of :mod:`nirspi_pipe.opencl_devices`.
    """

    def __init__(
        self,
        m_mat: np.ndarray,
        rows: np.ndarray,
        cols: np.ndarray,
        colnorm: np.ndarray,
        k_max: int,
        device: str = "auto",
    ) -> None:
        import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

        self.cl = cl
        self.ctx, self.queue, self.k = opencl_context(device)
        self.dev = self.ctx.devices[0]
        self.n, self.m, self.k_max = int(m_mat.shape[0]), int(rows.size), int(k_max)
        mf = cl.mem_flags

        def ro(a: np.ndarray) -> Any:
            return cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))

        self.d_m = ro(np.asarray(m_mat, np.float64))
        self.d_rows = ro(rows.astype(np.int32))
        self.d_cols = ro(cols.astype(np.int32))
        self.d_colnorm = ro(np.asarray(colnorm, np.float64))
        most = min(
            int(self.dev.max_work_group_size),
            *(
                int(self.k[name].get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.dev))
                for name in ("pick", "gram", "tri")
            ),
        )

        gpu = is_gpu(self.dev)
        # power-of-two work-groups (tree reductions); a CPU device runs a work-group as a loop
        self.l_sel = _pow2_at_most(min(most, 256 if gpu else 16))
        self.l_gram = _pow2_at_most(min(most, 128 if gpu else 16))
        self.l_tri = _pow2_at_most(min(most, 256 if gpu else 16))
        wg_most = int(self.k["omp_wg"].get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.dev))
        self.l_wg = _pow2_at_most(min(wg_most, int(self.dev.max_work_group_size), 1024 if gpu else 16))
        self.gpu = gpu

    def default_mode(self) -> str:
        """``workgroup`` (the whole solve in one launch, one work-group per problem) for images up to
        :data:`WORKGROUP_MAX_N`, else ``kernels`` (six launches per atom, each over the whole device)."""
        return "workgroup" if self.n <= WORKGROUP_MAX_N else "kernels"

    def solve(
        self, ys: np.ndarray, weight: np.ndarray, tol: float, mode: str | None = None
    ) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
        """Solve the problems ``ys`` (``(B, m)``) with selection ``weight`` (``(N,)``); returns
        ``(coefficients (B, N), atoms (B,), stop reasons, relative residuals (B,))``. ``mode``:
        ``kernels``, ``workgroup`` or None (:meth:`default_mode`)."""
        mode = mode or self.default_mode()
        if mode not in MODES:
            raise ValueError(f"mode {mode!r} not in {MODES}")
        cl, q, kern = self.cl, self.queue, self.k
        ys = np.ascontiguousarray(np.atleast_2d(ys), np.float64)
        nb = ys.shape[0]
        n, m, big_k = self.n, self.m, self.k_max
        nn = n * n
        mf = cl.mem_flags
        ny = np.linalg.norm(ys, axis=1)
        st = np.zeros((nb, 4), np.int32)
        st[ny == 0.0, 1] = 4
        sd = np.zeros((nb, 3))
        sd[:, 2] = np.where(ny > 0, ny, 1.0)

        def buf(nbytes: int) -> Any:
            return cl.Buffer(self.ctx, mf.READ_WRITE, max(8, int(nbytes)))

        d_y = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=ys)
        d_w = cl.Buffer(self.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.tile(np.asarray(weight, np.float64), nb))
        d_st = cl.Buffer(self.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=st)
        d_sd = cl.Buffer(self.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=sd)
        d_r, d_t, d_g, d_aty = buf(8 * nb * nn), buf(8 * nb * nn), buf(8 * nb * nn), buf(8 * nb * nn)
        d_lr, d_lc = buf(8 * nb * big_k * big_k), buf(8 * nb * big_k * big_k)
        d_c, d_wv, d_z, d_s = (buf(8 * nb * big_k) for _ in range(4))
        d_sup = buf(4 * nb * big_k)
        for d, nbytes in ((d_r, 8 * nb * nn), (d_s, 8 * nb * big_k), (d_z, 8 * nb * big_k)):
            cl.enqueue_fill_buffer(q, d, np.float64(0.0), 0, nbytes)
        i32, ni = np.int32, np.int32(n)
        if mode == "workgroup":
            lw = self.l_wg
            kern["omp_wg"](
                q, (lw * nb,), (lw,),
                self.d_m, self.d_rows, self.d_cols, self.d_colnorm, d_y, d_g, d_w, d_aty, d_r, d_t,
                d_lr, d_lc, d_c, d_wv, d_z, d_s, d_sup, d_st, d_sd, ni, i32(m), i32(big_k), np.float64(tol),
                cl.LocalMemory(8 * lw), cl.LocalMemory(4 * lw),
            )  # fmt: skip
            cl.enqueue_copy(q, st, d_st)
            return self._finish(q, st, sd, d_sup, d_s, d_sd, ny)
        # A^T y: scatter, then the two products
        kern["scatter_y"](q, (m, nb), None, d_r, self.d_rows, self.d_cols, d_y, ni, i32(m))
        kern["mtr"](q, (nn, nb), None, self.d_m, d_r, d_t, d_st, ni, i32(1))
        kern["tm_init"](q, (nn, nb), None, d_t, self.d_m, d_g, d_aty, ni)
        # the per-atom kernels: arguments set once, then only enqueued
        sel, gram, tri, syn, mtr, tmu = (kern[k] for k in ("pick", "gram", "tri", "synth", "mtr", "tm_upd"))
        sel.set_args(d_g, d_w, d_st, i32(nn), cl.LocalMemory(8 * self.l_sel), cl.LocalMemory(4 * self.l_sel))
        gram.set_args(
            self.d_m,
            self.d_rows,
            self.d_cols,
            d_sup,
            d_c,
            d_st,
            ni,
            i32(m),
            i32(big_k),
            cl.LocalMemory(8 * self.l_gram),
        )
        tri.set_args(
            d_lr, d_lc, d_c, d_wv, d_z, d_s, d_sup, d_aty, self.d_colnorm, d_st, d_sd,
            i32(nn), i32(big_k), np.float64(tol), cl.LocalMemory(8 * self.l_tri),
        )  # fmt: skip
        syn.set_args(self.d_m, self.d_rows, self.d_cols, d_sup, d_lr, d_r, d_st, ni, i32(m), i32(big_k))
        mtr.set_args(self.d_m, d_r, d_t, d_st, ni, i32(0))
        tmu.set_args(d_t, self.d_m, d_g, d_st, d_sd, ni)
        enq = cl.enqueue_nd_range_kernel
        g_sel, l_sel = (self.l_sel, nb), (self.l_sel, 1)
        g_tri, l_tri = (self.l_tri, nb), (self.l_tri, 1)
        g_mn, g_nn = (m, nb), (nn, nb)
        done_iters, chunk = 0, 32
        while True:
            todo = int(np.max(big_k - st[:, 0])) if np.any(st[:, 1] == 0) else 0
            todo = min(todo, chunk)
            for _ in range(todo):
                groups = max(1, min(done_iters, big_k))  # the support has at most done_iters atoms
                enq(q, sel, g_sel, l_sel)
                enq(q, gram, (groups * self.l_gram, nb), (self.l_gram, 1))
                enq(q, tri, g_tri, l_tri)
                enq(q, syn, g_mn, None)
                enq(q, mtr, g_nn, None)
                enq(q, tmu, g_nn, None)
                done_iters += 1
            cl.enqueue_copy(q, st, d_st)  # blocking: one small read per chunk
            if todo == 0 or not np.any(st[:, 1] == 0):
                break
            chunk *= 4
        return self._finish(q, st, sd, d_sup, d_s, d_sd, ny)

    def _finish(
        self, q: Any, st: np.ndarray, sd: np.ndarray, d_sup: Any, d_s: Any, d_sd: Any, ny: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
        """Read the supports and coefficients back (the solve's last reads) and scatter them."""
        cl, nb, big_k, nn = self.cl, st.shape[0], self.k_max, self.n * self.n
        sup = np.empty((nb, big_k), np.int32)
        coef = np.empty((nb, big_k))
        cl.enqueue_copy(q, sup, d_sup)
        cl.enqueue_copy(q, coef, d_s)
        cl.enqueue_copy(q, sd, d_sd)
        atoms = st[:, 0].astype(np.int64)
        out = np.zeros((nb, nn))
        res = np.ones(nb)
        for b in range(nb):
            k = int(atoms[b])
            out[b, sup[b, :k]] = coef[b, :k]
            if ny[b] == 0.0:
                res[b] = 0.0
            elif k:
                res[b] = float(np.sqrt(max(ny[b] * ny[b] - sd[b, 0], 0.0))) / ny[b]
        return out, atoms, [STOP_REASONS[int(c)] for c in st[:, 1]], res
