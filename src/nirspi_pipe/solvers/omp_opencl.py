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
binary in its on-disk cache.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.accel import is_gpu
from nirspi_pipe.accel import opencl_context as accel_context
from nirspi_pipe.errors import NirspiError

__all__ = ["DeviceOmp", "opencl_context", "gpu_available", "STOP_REASONS"]

#: Stop codes of the device state, by index (0: still running).
STOP_REASONS = ("running", "max_atoms", "exhausted", "residual_tol", "zero_measurements")

_SOURCE = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define TIE_RTOL %(tie_rtol)r
/* int state per problem: [k, stop, p, upd]; double state: [z2, zk, ny] */
#define SI 4
#define SD 3

__kernel void scatter_y(__global double *R, __global const int *rows, __global const int *cols,
                        __global const double *y, const int n, const int m) {
    const int t = get_global_id(0), b = get_global_id(1);
    if (t < m) R[b * n * n + rows[t] * n + cols[t]] = y[b * m + t];
}

/* T = M^T R : T[a, j] = sum_i M[i, a] R[i, j]; only where the problem updates (or always: init) */
__kernel void mtr(__global const double *M, __global const double *R, __global double *T,
                  __global const int *st, const int n, const int always) {
    const int e = get_global_id(0), b = get_global_id(1);
    if (e >= n * n || !(always || st[b * SI + 3])) return;
    const int a = e / n, j = e - (e / n) * n;
    __global const double *Rb = R + b * n * n;
    double s = 0.0;
    for (int i = 0; i < n; ++i) s += M[i * n + a] * Rb[i * n + j];
    T[b * n * n + e] = s;
}

/* g = aty = T M (the first correlation A^T y) */
__kernel void tm_init(__global const double *T, __global const double *M, __global double *g,
                      __global double *aty, const int n) {
    const int e = get_global_id(0), b = get_global_id(1);
    if (e >= n * n) return;
    const int a = e / n, c = e - (e / n) * n;
    __global const double *Tb = T + b * n * n;
    double s = 0.0;
    for (int j = 0; j < n; ++j) s += Tb[a * n + j] * M[j * n + c];
    g[b * n * n + e] = s;
    aty[b * n * n + e] = s;
}

/* g -= z_k (T M): the residual lost z_k q_k */
__kernel void tm_upd(__global const double *T, __global const double *M, __global double *g,
                     __global const int *st, __global const double *sd, const int n) {
    const int e = get_global_id(0), b = get_global_id(1);
    if (e >= n * n || !st[b * SI + 3]) return;
    const int a = e / n, c = e - (e / n) * n;
    __global const double *Tb = T + b * n * n;
    double s = 0.0;
    for (int j = 0; j < n; ++j) s += Tb[a * n + j] * M[j * n + c];
    g[b * n * n + e] += -sd[b * SD + 1] * s;
}

/* the best score and the lowest index within the tie window; one work-group per problem. No
   return after a barrier: every work-item reaches every barrier (PoCL runs a work-group as loops
   between barriers and mis-ran kernels that returned between two of them). */
__kernel void pick(__global const double *g, __global double *wgt, __global int *st, const int N,
                   __local double *red, __local int *redi) {
    const int lid = get_local_id(0), L = get_local_size(0), b = get_group_id(1);
    __global int *s = st + b * SI;
    const int stopped = s[1];
    __global const double *gb = g + b * N;
    __global double *wb = wgt + b * N;
    double best = 0.0;
    for (int e = lid; e < N && !stopped; e += L) best = fmax(best, fabs(gb[e]) * wb[e]);
    red[lid] = best;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = L / 2; h > 0; h >>= 1) {
        if (lid < h) red[lid] = fmax(red[lid], red[lid + h]);
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    best = red[0];
    const int found = !stopped && best > 0.0;
    const double thr = best * (1.0 - TIE_RTOL);
    int first = N;
    for (int e = lid; e < N && found; e += L) {
        if (fabs(gb[e]) * wb[e] >= thr) { first = e; break; }
    }
    redi[lid] = first;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = L / 2; h > 0; h >>= 1) {
        if (lid < h) redi[lid] = min(redi[lid], redi[lid + h]);
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0 && !stopped) {
        s[3] = 0;
        if (!found) {
            s[1] = 2;
        } else {
            const int p = redi[0];
            s[2] = p;
            wb[p] = 0.0;
        }
    }
}

/* c_j = a_{s_j} . a_p for the support's atoms j < k: work-group j of problem b */
__kernel void gram(__global const double *M, __global const int *rows, __global const int *cols,
                   __global const int *sup, __global double *cv, __global const int *st,
                   const int n, const int m, const int K, __local double *red) {
    const int lid = get_local_id(0), L = get_local_size(0), j = get_group_id(0), b = get_group_id(1);
    __global const int *s = st + b * SI;
    const int live = !s[1] && j < s[0];
    const int p = live ? s[2] : 0, ap = p / n, bp = p - (p / n) * n;
    const int q = live ? sup[b * K + j] : 0, aq = q / n, bq = q - (q / n) * n;
    double acc = 0.0;
    for (int t = lid; t < m && live; t += L) {
        const int r = rows[t] * n, c = cols[t] * n;
        acc += (M[r + aq] * M[c + bq]) * (M[r + ap] * M[c + bp]);
    }
    red[lid] = acc;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = L / 2; h > 0; h >>= 1) {
        if (lid < h) red[lid] += red[lid + h];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0 && live) cv[b * K + j] = red[0];
}

inline double wg_sum(__local double *red, double v, int lid, int L) {
    barrier(CLK_LOCAL_MEM_FENCE);
    red[lid] = v;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = L / 2; h > 0; h >>= 1) {
        if (lid < h) red[lid] += red[lid + h];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    const double out = red[0];
    barrier(CLK_LOCAL_MEM_FENCE);
    return out;
}

/* The factor update of omp_core for the picked atom; one work-group per problem (no return
   after a barrier, as in pick). */
__kernel void tri(__global double *Lr, __global double *Lc, __global const double *cv, __global double *wv,
                  __global double *zv, __global double *ss, __global int *sup, __global const double *aty,
                  __global const double *colnorm, __global int *st, __global double *sd,
                  const int N, const int K, const double tol, __local double *red) {
    const int lid = get_local_id(0), L = get_local_size(0), b = get_group_id(1);
    __global int *s = st + b * SI;
    __global double *d8 = sd + b * SD;
    const int stopped = s[1];
    const int k = stopped ? 0 : s[0], p = stopped ? 0 : s[2];
    __global double *Lrb = Lr + (long)b * K * K, *Lcb = Lc + (long)b * K * K;
    __global const double *c = cv + b * K;
    __global double *w = wv + b * K, *z = zv + b * K, *sb = ss + b * K;
    const double a2 = colnorm[p] * colnorm[p];
    /* w = L^-1 c: row i of L^-1 is column i of Lc's storage (Lc[j*K + i] = Linv[i][j]) */
    double ww = 0.0, wz = 0.0;
    for (int i = lid; i < k; i += L) {
        double acc = 0.0;
        for (int j = 0; j <= i; ++j) acc += Lcb[j * K + i] * c[j];
        w[i] = acc;
        ww += acc * acc;
        wz += acc * z[i];
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
    ww = wg_sum(red, ww, lid, L);
    wz = wg_sum(red, wz, lid, L);
    const double d2 = a2 - ww;
    /* d2 too small: the atom depends on the support; it is skipped (upd stays 0) */
    const int ok = !stopped && (d2 > 1e-20 * a2);
    const double d = sqrt(ok ? d2 : 1.0), minv = -1.0 / d;
    const double zk = ok ? (aty[b * N + p] - wz) / d : 0.0;
    /* new row of L^-1: -(w^T L^-1)/d, then 1/d on the diagonal */
    for (int j = lid; j < k && ok; j += L) {
        double acc = 0.0;
        for (int i = j; i < k; ++i) acc += w[i] * Lrb[i * K + j];
        const double r = acc * minv;
        Lrb[k * K + j] = r;
        Lcb[j * K + k] = r;
        sb[j] += zk * r;
    }
    if (lid == 0 && ok) {
        const double r = 1.0 / d;
        Lrb[k * K + k] = r;
        Lcb[k * K + k] = r;
        sb[k] += zk * r;
        z[k] = zk;
        sup[b * K + k] = p;
        const double z2 = d8[0] + zk * zk;
        d8[0] = z2;
        d8[1] = zk;
        const int k1 = k + 1;
        s[0] = k1;
        const double ny = d8[2];
        const double res = sqrt(fmax(ny * ny - z2, 0.0)) / ny;
        if (res <= tol) s[1] = 3;
        else if (k1 >= K) s[1] = 1;
        else s[3] = 1;
    }
}

/* q_k = A_S (row k-1 of L^-1) at the measured cells, on the Hadamard grid */
__kernel void synth(__global const double *M, __global const int *rows, __global const int *cols,
                    __global const int *sup, __global const double *Lr, __global double *R,
                    __global const int *st, const int n, const int m, const int K) {
    const int t = get_global_id(0), b = get_global_id(1);
    __global const int *s = st + b * SI;
    if (t >= m || !s[3]) return;
    const int kk = s[0] - 1;
    __global const double *row = Lr + (long)b * K * K + (long)kk * K;
    __global const int *sp = sup + b * K;
    const int r = rows[t] * n, c = cols[t] * n;
    double acc = 0.0;
    for (int j = 0; j <= kk; ++j) {
        const int q = sp[j], aq = q / n, bq = q - (q / n) * n;
        acc += row[j] * (M[r + aq] * M[c + bq]);
    }
    R[b * n * n + r + cols[t]] = acc;
}
/* The whole solve of one problem in one work-group, one launch for all atoms (and one work-group
   per problem of a batch): the steps of the kernels above, separated by barriers. No launch per
   atom, which on a GPU costs more than a small problem's arithmetic. */
__kernel void omp_wg(__global const double *M, __global const int *rows, __global const int *cols,
                     __global const double *colnorm, __global const double *y, __global double *g,
                     __global double *wgt, __global double *aty, __global double *R, __global double *T,
                     __global double *Lr, __global double *Lc, __global double *cv, __global double *wv,
                     __global double *zv, __global double *ss, __global int *sup, __global int *st,
                     __global double *sd, const int n, const int m, const int K, const double tol,
                     __local double *red, __local int *redi) {
    const int lid = get_local_id(0), L = get_local_size(0), b = get_group_id(0);
    const int N = n * n;
    __global int *s = st + b * SI;
    __global double *d8 = sd + b * SD;
    __global double *Rb = R + b * N, *Tb = T + b * N, *gb = g + b * N, *wb = wgt + b * N, *ab = aty + b * N;
    __global double *Lrb = Lr + (long)b * K * K, *Lcb = Lc + (long)b * K * K;
    __global double *c = cv + b * K, *w = wv + b * K, *z = zv + b * K, *sb = ss + b * K;
    __global int *sp = sup + b * K;
    for (int e = lid; e < N; e += L) Rb[e] = 0.0;
    barrier(CLK_GLOBAL_MEM_FENCE);
    for (int t = lid; t < m; t += L) Rb[rows[t] * n + cols[t]] = y[b * m + t];
    barrier(CLK_GLOBAL_MEM_FENCE);
    for (int e = lid; e < N; e += L) {
        const int a = e / n, j = e - (e / n) * n;
        double acc = 0.0;
        for (int i = 0; i < n; ++i) acc += M[i * n + a] * Rb[i * n + j];
        Tb[e] = acc;
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
    for (int e = lid; e < N; e += L) {
        const int a = e / n, cc = e - (e / n) * n;
        double acc = 0.0;
        for (int j = 0; j < n; ++j) acc += Tb[a * n + j] * M[j * n + cc];
        gb[e] = acc;
        ab[e] = acc;
    }
    while (1) {
        barrier(CLK_GLOBAL_MEM_FENCE);
        const int stopped = s[1], k = s[0];
        barrier(CLK_GLOBAL_MEM_FENCE);
        if (stopped) break;
        /* pick */
        double best = 0.0;
        for (int e = lid; e < N; e += L) best = fmax(best, fabs(gb[e]) * wb[e]);
        red[lid] = best;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int h = L / 2; h > 0; h >>= 1) {
            if (lid < h) red[lid] = fmax(red[lid], red[lid + h]);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        best = red[0];
        const int found = best > 0.0;
        const double thr = best * (1.0 - TIE_RTOL);
        int first = N;
        for (int e = lid; e < N && found; e += L) {
            if (fabs(gb[e]) * wb[e] >= thr) { first = e; break; }
        }
        redi[lid] = first;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int h = L / 2; h > 0; h >>= 1) {
            if (lid < h) redi[lid] = min(redi[lid], redi[lid + h]);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        const int p = found ? redi[0] : 0;
        barrier(CLK_GLOBAL_MEM_FENCE);
        if (lid == 0) {
            s[3] = 0;
            if (!found) s[1] = 2;
            else { s[2] = p; wb[p] = 0.0; }
        }
        if (!found) continue; /* uniform; the loop top sees the stop */
        /* gram: c_j = a_{s_j} . a_p, one work-item per support atom */
        const int ap = p / n, bp = p - (p / n) * n;
        for (int j = lid; j < k; j += L) {
            const int q = sp[j], aq = q / n, bq = q - (q / n) * n;
            double acc = 0.0;
            for (int t = 0; t < m; ++t) {
                const int r = rows[t] * n, cc = cols[t] * n;
                acc += (M[r + aq] * M[cc + bq]) * (M[r + ap] * M[cc + bp]);
            }
            c[j] = acc;
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
        /* tri */
        const double a2 = colnorm[p] * colnorm[p];
        double ww = 0.0, wz = 0.0;
        for (int i = lid; i < k; i += L) {
            double acc = 0.0;
            for (int j = 0; j <= i; ++j) acc += Lcb[j * K + i] * c[j];
            w[i] = acc;
            ww += acc * acc;
            wz += acc * z[i];
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
        ww = wg_sum(red, ww, lid, L);
        wz = wg_sum(red, wz, lid, L);
        const double d2 = a2 - ww;
        if (!(d2 > 1e-20 * a2)) continue; /* uniform: the atom is skipped */
        const double d = sqrt(d2), minv = -1.0 / d;
        const double zk = (ab[p] - wz) / d;
        for (int j = lid; j < k; j += L) {
            double acc = 0.0;
            for (int i = j; i < k; ++i) acc += w[i] * Lrb[i * K + j];
            const double r = acc * minv;
            Lrb[k * K + j] = r;
            Lcb[j * K + k] = r;
            sb[j] += zk * r;
        }
        int upd = 0;
        {
            const double r = 1.0 / d;
            const double z2 = d8[0] + zk * zk;
            const double ny = d8[2];
            const double res = sqrt(fmax(ny * ny - z2, 0.0)) / ny;
            upd = !(res <= tol) && k + 1 < K;
            barrier(CLK_GLOBAL_MEM_FENCE);
            if (lid == 0) {
                Lrb[k * K + k] = r;
                Lcb[k * K + k] = r;
                sb[k] += zk * r;
                z[k] = zk;
                sp[k] = p;
                d8[0] = z2;
                d8[1] = zk;
                s[0] = k + 1;
                if (res <= tol) s[1] = 3;
                else if (k + 1 >= K) s[1] = 1;
                else s[3] = 1;
            }
        }
        if (!upd) continue;
        barrier(CLK_GLOBAL_MEM_FENCE);
        /* synth: q_k on the measured cells */
        for (int t = lid; t < m; t += L) {
            const int r = rows[t] * n, cc = cols[t] * n;
            double acc = 0.0;
            for (int j = 0; j <= k; ++j) {
                const int q = sp[j], aq = q / n, bq = q - (q / n) * n;
                acc += Lrb[k * K + j] * (M[r + aq] * M[cc + bq]);
            }
            Rb[r + cols[t]] = acc;
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
        for (int e = lid; e < N; e += L) {
            const int a = e / n, j = e - (e / n) * n;
            double acc = 0.0;
            for (int i = 0; i < n; ++i) acc += M[i * n + a] * Rb[i * n + j];
            Tb[e] = acc;
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
        for (int e = lid; e < N; e += L) {
            const int a = e / n, cc = e - (e / n) * n;
            double acc = 0.0;
            for (int j = 0; j < n; ++j) acc += Tb[a * n + j] * M[j * n + cc];
            gb[e] += -zk * acc;
        }
    }
}
"""

_KERNELS = ("scatter_y", "mtr", "tm_init", "tm_upd", "pick", "gram", "tri", "synth", "omp_wg")


def kernel_source() -> str:
    """OpenCL C source of the device OMP."""
    from nirspi_pipe.solvers.common import TIE_RTOL  # start-up: loads scipy, charset_normalizer (210 ms here)

    return _SOURCE % {"tie_rtol": float(TIE_RTOL)}


@lru_cache(maxsize=4)
def opencl_context(device: str = "auto") -> tuple[Any, Any, dict[str, Any]]:
    """``(context, queue, kernels by name)`` on the device ``device`` names
    (:func:`nirspi_pipe.accel.opencl_device`), built once per process. Raises
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
    return ctx, queue, {k: cl.Kernel(program, k) for k in _KERNELS}


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
        device: a device spec of :mod:`nirspi_pipe.accel`.
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
