"""OpenCL back end of the fast-sweeping solvers (pyopencl; PoCL on the CPU here), float64.

The whole solve — every round of four sweeps, the KOQ boundary rule and the convergence test —
runs in one kernel launch on a single work-group. Work-items share the cells of one
anti-diagonal and meet at a barrier before the next diagonal: the parallel sweeping order of
Detrixhe, Gibou & Min (J. Comput. Phys. 2013), which is exactly the dependency structure of the
numpy path (:mod:`nirspi_pipe.sfs.sweeping`), so both do the same arithmetic in the same order.
``FP_CONTRACT`` is off so that no fused multiply-adds change the rounding: the two back ends agree
to ~1e-12 pixel (tested at 1e-9), whatever the number of work-items (the cells of a diagonal never
read each other: tests/test_parity.py runs 1, 8, 64 and the device's own).

How many work-items (:func:`default_local_size`): on a CPU device one, the serial sweep, which
PoCL compiles into a plain loop (the fastest there: docs/sfs.md has the numbers); on a GPU one per
cell of the longest diagonal, ``min(rows, cols)`` rounded up to a warp (32) and capped by the
kernel's work-group limit, so every diagonal is one parallel step. One work-group keeps the
solve to one launch (no per-diagonal launch latency: a round of a 256² grid is 2044 diagonals);
grids wider than the work-group limit loop over the diagonal inside each step.

A kernel is compiled twice: when its program is built (cached on disk) and, by PoCL, at its first
launch with a given local size (the work-group function, ~0.1–0.4 s here with a cold
``~/.cache/pocl``). :func:`warm_up`, called when an SFS stage is built, does both: it builds the
program and launches each kernel of the solve once on a 4×4 problem with the solve's local
sizes, so that neither compilation falls inside a timed solve.

The device is a spec of :mod:`nirspi_pipe.opencl_devices` (``auto``, ``cpu``, ``gpu``, ``P:D``).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.opencl_devices import choose, device_label, is_gpu, opencl_context
from nirspi_pipe.sfs.second_order import F_MAX, GAUSS_Q, HALF_PI, SLOPE_AVERAGES, slope_antiderivative
from nirspi_pipe.sfs.sweeping import BIG, SweepProblem, SweepResult

__all__ = ["solve_opencl", "opencl_available"]

#: Work-items of the sweeping kernels (``fsm``, ``fsm2``) on a CPU device: one is fastest there
#: (:func:`default_local_size`), and :func:`warm_up` launches with it.
LOCAL_SIZE = 1

#: Work-items of a GPU's sweeping work-group are a multiple of this (NVIDIA's warp; AMD's
#: wavefront is 32 or 64, a multiple of 32 either way).
GPU_WARP = 32

#: Work-group size of ``edges2`` (one work-item per pixel, the global size padded to a multiple;
#: the kernel returns past ``R*C``). Fixed rather than left to the driver: PoCL picks the local
#: size from the global size (4096 at 64², 961 at 31², ...) and compiles a work-group function
#: for each new one at its first launch, ~45 ms inside the solve of each new image size. 64 is as
#: fast as PoCL's own choice at 64²–256² (0.10/0.35/2.37 ms) and gives the same bits.
EDGES_LOCAL_SIZE = 64

#: Second-order upwind sweeping (``scheme: second_order``), the same arithmetic in the same order
#: as :func:`nirspi_pipe.sfs.second_order.update`; the edge slopes are computed on the host by
#: :func:`nirspi_pipe.sfs.second_order.edge_slopes` so that both back ends use identical inputs.
_KERNEL2 = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
#define BIG %(big)r
#define KNOWN (0.5 * BIG)
#define HALF_PI %(half_pi)r
#define GAUSS_Q %(gauss_q)r
#define F_MAX %(f_max)r

/* Mean of F over the edge between pixels 0 and 1 with cos^2 = 1/(1 + F^2) linear along it
   (second_order._mean_slope_from; v = slope_antiderivative, computed on the host). */
inline double mean_slope2(double f0, double v0, double f1, double v1) {
    f0 = fmin(f0, F_MAX);
    f1 = fmin(f1, F_MAX);
    const double q0 = f0 * f0, q1 = f1 * f1;
    const double g0 = 1.0 / (1.0 + q0), g1 = 1.0 / (1.0 + q1);
    const double h0 = q0 * g0, h1 = q1 * g1;
    const int hi0 = g0 >= 0.5, hi1 = g1 >= 0.5;
    const double d = (hi0 && hi1) ? h0 - h1 : g1 - g0;
    if (fabs(d) <= 5e-3 * fmin(g0 + g1, h0 + h1)) {
        const double gm = 0.5 * (g0 + g1), hm = 0.5 * (h0 + h1), ds = (g1 - g0) * GAUSS_Q;
        const double lo = sqrt(fmax(hm + ds, 0.0) / (gm - ds));
        const double up = sqrt(fmax(hm - ds, 0.0) / (gm + ds));
        return 0.5 * (lo + up);
    }
    return ((v1 - v0) + ((double)hi1 - (double)hi0) * HALF_PI) / d;
}

__kernel void edges2(__global const double *rhs, __global const double *v, const int R, const int C,
                     __global double *eh, __global double *ev) {
    const int k = get_global_id(0);
    if (k >= R * C) return;
    const int i = k / C, j = k - (k / C) * C;
    eh[k] = (j + 1 < C) ? mean_slope2(rhs[k], v[k], rhs[k + 1], v[k + 1]) : 0.0;
    ev[k] = (i + 1 < R) ? mean_slope2(rhs[k], v[k], rhs[k + C], v[k + C]) : 0.0;
}

inline double zat2(__global const double *z, int i, int j, int R, int C) {
    return (i >= 0 && i < R && j >= 0 && j < C) ? z[i * C + j] : BIG;
}

inline double eat2(__global const double *e, int i, int j, int R, int C) {
    return (i >= 0 && i < R && j >= 0 && j < C) ? e[i * C + j] : 0.0;
}

/* Upwind data of one axis (step (di, dj)): T, alpha, T1 and the slope F* (second_order.py). */
inline void axis2(__global const double *z, __global const double *e, int i, int j, int di, int dj,
                  int R, int C, double f, double *t, double *al, double *t1o, double *fso) {
    const double m1 = zat2(z, i - di, j - dj, R, C), p1 = zat2(z, i + di, j + dj, R, C);
    const int left = m1 <= p1;
    const double t1 = left ? m1 : p1;
    const double t2 = left ? zat2(z, i - 2 * di, j - 2 * dj, R, C) : zat2(z, i + 2 * di, j + 2 * dj, R, C);
#if COS2
    const double e1 = left ? eat2(e, i - di, j - dj, R, C) : eat2(e, i, j, R, C);
    const double e2 = left ? eat2(e, i - 2 * di, j - 2 * dj, R, C) : eat2(e, i + di, j + dj, R, C);
    const double f2 = 0.5 * (3.0 * e1 - e2);
    const int so = (t2 <= t1) && (f2 >= 0.5 * e1);
    *fso = so ? f2 : e1;
#else
    const int so = t2 <= t1;
    *fso = f;
#endif
    *t = so ? (4.0 * t1 - t2) / 3.0 : t1;
    *al = so ? 1.5 : 1.0;
    *t1o = t1;
}

/* One cell update (second_order.update); returns the decrease of z[c]. */
inline double cell2(__global double *z, __global const double *rhs, __global const double *eh,
                    __global const double *ev, int i, int j, int R, int C) {
    const int c = i * C + j;
    const double u = z[c], f = rhs[c];
    double tx, ax, t1x, fx, ty, ay, t1y, fy;
    axis2(z, eh, i, j, 0, 1, R, C, f, &tx, &ax, &t1x, &fx);
    axis2(z, ev, i, j, 1, 0, R, C, f, &ty, &ay, &t1y, &fy);
    const int kx = t1x < KNOWN, ky = t1y < KNOWN;
    const double ux = kx ? tx + fx / ax : BIG;
    const double uy = ky ? ty + fy / ay : BIG;
    const double u1 = fmin(ux, uy);
    const double a = (fy * ax) * (fy * ax), b = (fx * ay) * (fx * ay);
    const double sa = a + b, dt = tx - ty;
    const double disc = sa * ((fx * fy) * (fx * fy)) - (a * b) * (dt * dt);
    const double u2 = (a * tx + b * ty + sqrt(fmax(disc, 0.0))) / (sa > 0.0 ? sa : 1.0);
    const int ok = kx && ky && (sa > 0.0) && (disc >= 0.0) && (u2 >= t1x) && (u2 >= t1y);
    const double nw = fmin(u, ok ? u2 : u1);
    z[c] = nw;
    return u - nw;
}

inline void mark2(__global uchar *dirty, int i, int j, int R, int C) {
    if (i >= 0 && i < R && j >= 0 && j < C) dirty[i * C + j] = 1;
}

/* dirty[c]: a value in the stencil of c changed since c was last updated. A clean cell would
   compute the same z-bar as last time, and min(z, z-bar) = z, so skipping it changes nothing:
   results are identical to updating every cell (the numpy path), the later rounds are cheap. */
__kernel void fsm2(__global double *z, __global const double *rhs,
                   __global const double *eh, __global const double *ev,
                   __global const uchar *upd, __global uchar *dirty, const int R, const int C,
                   const int max_rounds, const double tol,
                   __global double *out, __local double *red)
{
    const int lid = get_local_id(0), L = get_local_size(0);
    double rc = INFINITY;
    int rounds = 0, conv = 0;
    for (int round = 0; round < max_rounds; ++round) {
        double my = 0.0;
        for (int o = 0; o < 4; ++o) {
            const int flip_i = (o == 1 || o == 2), flip_j = (o == 2 || o == 3);
            for (int d = 0; d < R + C - 1; ++d) {
                const int i0 = max(0, d - (C - 1)), i1 = min(R - 1, d);
                for (int ii = i0 + lid; ii <= i1; ii += L) {
                    const int jj = d - ii;
                    const int i = flip_i ? R - 1 - ii : ii;
                    const int j = flip_j ? C - 1 - jj : jj;
                    const int c = i * C + j;
                    if (!upd[c] || !dirty[c]) continue;
                    dirty[c] = 0;
                    const double dec = cell2(z, rhs, eh, ev, i, j, R, C);
                    if (dec > 0.0) {
                        my = fmax(my, dec);
                        mark2(dirty, i - 1, j, R, C); mark2(dirty, i + 1, j, R, C);
                        mark2(dirty, i - 2, j, R, C); mark2(dirty, i + 2, j, R, C);
                        mark2(dirty, i, j - 1, R, C); mark2(dirty, i, j + 1, R, C);
                        mark2(dirty, i, j - 2, R, C); mark2(dirty, i, j + 2, R, C);
                    }
                }
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
        }
        red[lid] = my;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {
            double m = 0.0;
            for (int k = 0; k < L; ++k) m = fmax(m, red[k]);
            red[0] = m;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        rc = red[0];
        barrier(CLK_LOCAL_MEM_FENCE);
        rounds += 1;
        if (rc <= tol) { conv = 1; break; }
    }
    if (lid == 0) { out[0] = 4.0 * rounds; out[1] = rc; out[2] = conv; }
}
"""

_KERNEL = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
#define BIG %(big)r

inline double ham(double p, double q, double xh, double yh) {
#if MODEL == 0
    return sqrt(p * p + q * q);
#else
    double t = xh * p + yh * q + 1.0;
    return sqrt(p * p + q * q + t * t);
#endif
}

inline double zat(__global const double *z, int i, int j, int R, int C) {
    return (i >= 0 && i < R && j >= 0 && j < C) ? z[i * C + j] : BIG;
}

__kernel void fsm(__global double *z, __global const double *rhs,
                  __global const uchar *upd, __global const uchar *fixed,
                  __global const double *xh, __global const double *yh,
                  const int R, const int C, const double sx, const double sy,
                  const double two_over_f, const int max_rounds, const double tol,
                  __global double *out, __local double *red)
{
    const int lid = get_local_id(0), L = get_local_size(0);
    const double inv_s = 1.0 / (sx + sy);
    double rc = INFINITY;
    int rounds = 0, conv = 0;
    for (int round = 0; round < max_rounds; ++round) {
        double my = 0.0;
        for (int o = 0; o < 4; ++o) {
            for (int d = 0; d < R + C - 1; ++d) {
                const int i0 = max(0, d - (C - 1)), i1 = min(R - 1, d);
                for (int ii = i0 + lid; ii <= i1; ii += L) {
                    const int jj = d - ii;
                    const int i = (o == 1 || o == 2) ? R - 1 - ii : ii;
                    const int j = (o == 2 || o == 3) ? C - 1 - jj : jj;
                    const int c = i * C + j;
                    if (!upd[c]) continue;
                    const double zc = z[c];
                    const double zw = zat(z, i, j - 1, R, C), ze = zat(z, i, j + 1, R, C);
                    const double zn = zat(z, i - 1, j, R, C), zs = zat(z, i + 1, j, R, C);
                    const double f = rhs[c];
                    double nw;
#if SCHEME == 0
                    const double p = 0.5 * (ze - zw), q = 0.5 * (zs - zn);
                    const double h = ham(p, q, xh[j], yh[i]);
                    const double base = -h + 0.5 * sx * (ze + zw) + 0.5 * sy * (zn + zs);
#if MODEL == 2
                    const double s = sx + sy;
                    double w = fmin(zc, (base + f) / s);
                    for (int k = 0; k < 4; ++k) {
                        const double e = f * exp(-two_over_f * w);
                        const double g = s * w - e - base;
                        w = w - g / (s + two_over_f * e);
                    }
                    nw = w;
#else
                    nw = (f + base) * inv_s;
#endif
#else
                    const double ax = fmin(zw, ze), by = fmin(zn, zs), dd = ax - by;
                    if (fabs(dd) >= f) nw = fmin(ax, by) + f;
                    else nw = 0.5 * (ax + by + sqrt(fmax(2.0 * f * f - dd * dd, 0.0)));
#endif
                    nw = fmin(zc, nw);
                    z[c] = nw;
                    my = fmax(my, zc - nw);
                }
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
#if SCHEME == 0
            /* KOQ boundary rule Z1 = min(max(2 Z2 - Z3, Z3), Z1): top, bottom, left, right. */
            if (R >= 3) {
                for (int side = 0; side < 2; ++side) {
                    const int e = side ? R - 1 : 0, a = side ? R - 2 : 1, b = side ? R - 3 : 2;
                    for (int j = lid; j < C; j += L) {
                        if (fixed[e * C + j]) continue;
                        const double old = z[e * C + j];
                        const double nw = fmin(fmax(2.0 * z[a * C + j] - z[b * C + j], z[b * C + j]), old);
                        z[e * C + j] = nw;
                        my = fmax(my, old - nw);
                    }
                    barrier(CLK_GLOBAL_MEM_FENCE);
                }
            }
            if (C >= 3) {
                for (int side = 0; side < 2; ++side) {
                    const int e = side ? C - 1 : 0, a = side ? C - 2 : 1, b = side ? C - 3 : 2;
                    for (int i = lid; i < R; i += L) {
                        if (fixed[i * C + e]) continue;
                        const double old = z[i * C + e];
                        const double nw = fmin(fmax(2.0 * z[i * C + a] - z[i * C + b], z[i * C + b]), old);
                        z[i * C + e] = nw;
                        my = fmax(my, old - nw);
                    }
                    barrier(CLK_GLOBAL_MEM_FENCE);
                }
            }
#endif
        }
        red[lid] = my;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {
            double m = 0.0;
            for (int k = 0; k < L; ++k) m = fmax(m, red[k]);
            red[0] = m;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        rc = red[0];
        barrier(CLK_LOCAL_MEM_FENCE);
        rounds += 1;
        if (rc <= tol) { conv = 1; break; }
    }
    if (lid == 0) { out[0] = 4.0 * rounds; out[1] = rc; out[2] = conv; }
}
"""


@lru_cache(maxsize=8)
def _context(device: str = "auto") -> tuple[Any, Any]:
    """``(context, queue)`` on the device ``device`` names (:func:`nirspi_pipe.opencl_devices.opencl_device`;
    cached here too, so that its cache says whether this process made one)."""
    return opencl_context(device)


@lru_cache(maxsize=16)
def _program(model: int, scheme: int, device: str = "auto"):
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

    ctx, _ = _context(device)
    src = _KERNEL % {"big": BIG}
    prg = cl.Program(ctx, src).build(options=[f"-DMODEL={model}", f"-DSCHEME={scheme}"])
    return cl.Kernel(prg, "fsm")


@lru_cache(maxsize=4)
def _program2(cos2: int, device: str = "auto"):
    """``(fsm2, edges2, local size of edges2)`` (at most :data:`EDGES_LOCAL_SIZE`)."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

    ctx, _ = _context(device)
    prg = cl.Program(ctx, kernel2_source()).build(options=[f"-DCOS2={int(cos2)}"])
    edges = cl.Kernel(prg, "edges2")
    most = edges.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, ctx.devices[0])
    return cl.Kernel(prg, "fsm2"), edges, max(1, min(EDGES_LOCAL_SIZE, int(most)))


def default_local_size(kernel: Any, device: str, rows: int, cols: int) -> int:
    """Work-items of the sweeping kernel for an ``rows × cols`` grid on ``device``.

    A CPU device gets :data:`LOCAL_SIZE` (1: PoCL compiles the serial sweep into a plain loop,
    the fastest there, measured in docs/sfs.md). A GPU gets one work-item per cell of the longest
    anti-diagonal, ``min(rows, cols)``, rounded up to a multiple of :data:`GPU_WARP` and capped by
    the kernel's largest work-group: the cells of one diagonal are independent (Detrixhe, Gibou &
    Min 2013), so each diagonal is one parallel step between two barriers of the work-group.
    """
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

    ctx, _ = _context(device)
    dev = ctx.devices[0]
    if not is_gpu(dev):
        return LOCAL_SIZE
    most = int(kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, dev))
    want = -(-max(1, min(rows, cols)) // GPU_WARP) * GPU_WARP
    return max(1, min(most, want))


def kernel2_source() -> str:
    """OpenCL C source of the second-order kernels (``fsm2``, ``edges2``)."""
    consts = {"big": BIG, "half_pi": HALF_PI, "gauss_q": GAUSS_Q, "f_max": F_MAX}
    return _KERNEL2 % {k: float(v) for k, v in consts.items()}


def opencl_available(scheme: str = "godunov", device: str = "auto") -> bool:
    """True when pyopencl finds a float64-capable device (``device``,
    :func:`nirspi_pipe.opencl_devices.opencl_device`) that builds the sweeping kernel for ``scheme`` (PoCL
    fails on CPUs its LLVM does not know, e.g. ``unknown target CPU 'generic'``)."""
    try:
        if scheme == "second_order":
            _program2(1, device)
        else:
            _program(0, 1, device)
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return False
    return True


def warm_up(
    model: int, scheme: str, slope_average: str = "cos2", local_size: int | None = None, device: str = "auto"
) -> bool:
    """Build (or fetch from the on-disk caches) the exact kernels a solve with ``model`` and
    ``scheme`` will launch, and launch each once on a 4×4 problem with the solve's local sizes
    (:func:`_warm_launch`), so that compilation is never part of a stage's time; True when that
    works, False on any failure (the caller falls back to numpy). Once per process and program.
    ``local_size`` None: the device's (:func:`default_local_size`; on a GPU it grows with the
    grid, and NVIDIA's driver compiles once per program, not per local size). Called by the SFS
    stages' ``__post_init__``."""
    cos2 = slope_average if scheme == "second_order" else "cos2"  # the others ignore it
    try:
        if scheme == "second_order":
            kernels: Any = _program2(int(cos2 == "cos2"), device)
            sweep = kernels[0]
        else:
            kernels = sweep = _program(int(model), 0 if scheme == "lax_friedrichs" else 1, device)
        lsz = default_local_size(sweep, device, 64, 64) if local_size is None else int(max(1, local_size))
        _warm_launch(int(model), scheme, cos2, lsz, kernels, device)
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return False
    return True


@lru_cache(maxsize=16)
def _warm_launch(model: int, scheme: str, slope_average: str, local_size: int, kernels: Any, device: str) -> None:
    """Run :func:`solve_opencl` once on a 4×4 problem: the buffers, pyopencl's argument setter
    and PoCL's per-local-size work-group function of every kernel the solve launches (``fsm``;
    ``edges2`` and ``fsm2``) are made here. ``kernels`` (the built program's, what the solve
    will fetch) keys the cache, so a rebuilt program is launched again. Solves the solvers refuse
    (Godunov or second order for a perspective model) are only built: :func:`solve_opencl`
    raises for them whatever the warm-up did."""
    if scheme in ("godunov", "second_order") and model != 0:
        return
    n = 4
    fixed = np.zeros((n, n), dtype=bool)
    fixed[1, 1] = model != 2  # the fall-off model needs no boundary data
    init = np.where(fixed, 0.0, 1.0 if model == 2 else BIG)
    coords = (np.arange(n) + 0.5 - n / 2) / (2.0 * n)
    problem = SweepProblem(np.full((n, n), 1.5), fixed, init, model, coords, coords, 2.0 * n)
    solve_opencl(problem, scheme, max_sweeps=4, local_size=local_size, slope_average=slope_average, device=device)


def resolve_backend(
    backend: str, model: int, scheme: str, slope_average: str = "cos2", device: str = "auto", size: int = 64
) -> str:
    """``auto`` → ``opencl`` when a device builds and runs this solve's kernels (:func:`warm_up`)
    and the measured choice for that device and image side ``size`` is OpenCL
    (:func:`nirspi_pipe.opencl_devices.choose`), else ``numpy``; ``numpy``/``opencl`` are returned as given
    (``opencl`` warmed up)."""
    if backend == "numpy":
        return backend
    ok = warm_up(model, scheme, slope_average, device=device)
    if backend == "auto":
        if not ok:
            return "numpy"

        return choose("sfs", _context(device)[0].devices[0], size)[0]
    return backend


def device_name(device: str = "auto") -> str:
    """The record's name of the device ``device`` names (``platform / device (GPU|CPU)``)."""
    return device_label(_context(device)[0].devices[0])


def solve_opencl(
    problem: SweepProblem,
    scheme: str = "lax_friedrichs",
    tol: float = 1e-4,
    max_sweeps: int = 2000,
    local_size: int | None = None,
    slope_average: str = "cos2",
    device: str = "auto",
) -> SweepResult:
    """Same contract as :func:`nirspi_pipe.sfs.sweeping.solve_numpy`, on an OpenCL device.

    ``local_size`` work-items share each anti-diagonal (None: :func:`default_local_size`, one on
    a CPU device, where the kernel is then plain compiled Gauss–Seidel and skips the barrier
    bookkeeping; the longest diagonal on a GPU). Every local size gives the same bits: the cells
    of one diagonal never read each other. ``slope_average`` is used by
    ``scheme="second_order"`` only; ``device`` is a spec of :mod:`nirspi_pipe.opencl_devices`.
    """
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

    if scheme == "second_order":
        return _solve_second_order(problem, tol, max_sweeps, local_size, slope_average, device)

    if scheme == "godunov" and problem.model != 0:
        raise ValueError("the Godunov update is implemented for the eikonal (model 0) only")
    ctx, queue = _context(device)
    kernel = _program(int(problem.model), 0 if scheme == "lax_friedrichs" else 1, device)
    rows, cols = problem.rhs.shape
    upd = ~problem.fixed
    if scheme == "lax_friedrichs":
        upd = upd.copy()
        if rows >= 3 and cols >= 3:
            upd[0, :] = upd[-1, :] = upd[:, 0] = upd[:, -1] = False
        else:
            upd[:] = False
    mf = cl.mem_flags
    z = np.ascontiguousarray(problem.init, dtype=np.float64).copy()
    xh = problem.xhat if problem.xhat is not None else np.zeros(cols)
    yh = problem.yhat if problem.yhat is not None else np.zeros(rows)
    bufs = [
        cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=z),
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(problem.rhs, np.float64)),
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(upd, np.uint8)),
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(problem.fixed, np.uint8)),
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(xh, np.float64)),
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(yh, np.float64)),
    ]
    out = np.zeros(3)
    out_buf = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
    sx, sy = problem.sigmas()
    max_rounds = max(1, -(-int(max_sweeps) // 4))
    lsz = default_local_size(kernel, device, rows, cols) if local_size is None else int(max(1, local_size))
    kernel(
        queue,
        (lsz,),
        (lsz,),
        *bufs,
        np.int32(rows),
        np.int32(cols),
        np.float64(sx),
        np.float64(sy),
        np.float64(2.0 / float(problem.focal_px)),
        np.int32(max_rounds),
        np.float64(tol),
        out_buf,
        cl.LocalMemory(8 * lsz),
    )
    cl.enqueue_copy(queue, z, bufs[0])
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    return SweepResult(z, int(out[0]), float(out[1]), bool(out[2]))


def _solve_second_order(
    problem: SweepProblem, tol: float, max_sweeps: int, local_size: int | None, slope_average: str, device: str
) -> SweepResult:
    """``scheme="second_order"`` on the OpenCL device (kernel ``fsm2``)."""
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (64 ms here)

    if problem.model != 0:
        raise ValueError("the second-order scheme is implemented for the eikonal (model 0) only")
    if slope_average not in SLOPE_AVERAGES:
        raise ValueError(f"slope_average {slope_average!r} not in {SLOPE_AVERAGES}")
    cos2 = slope_average == "cos2"
    ctx, queue = _context(device)
    kernel, edges, edges_lsz = _program2(int(cos2), device)
    rows, cols = problem.rhs.shape
    rhs = np.ascontiguousarray(np.minimum(problem.rhs, F_MAX), np.float64)
    mf = cl.mem_flags
    z = np.ascontiguousarray(problem.init, dtype=np.float64).copy()
    rhs_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rhs)
    eh_buf = cl.Buffer(ctx, mf.READ_WRITE, rhs.nbytes)
    ev_buf = cl.Buffer(ctx, mf.READ_WRITE, rhs.nbytes)
    if cos2:  # edge slopes on the device; the per-pixel arcsin on the host (same bits as numpy)
        v_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=slope_antiderivative(rhs))
        glob = -(-rows * cols // edges_lsz) * edges_lsz  # padded: the kernel returns past R*C
        edges(queue, (glob,), (edges_lsz,), rhs_buf, v_buf, np.int32(rows), np.int32(cols), eh_buf, ev_buf)
    bufs = [
        cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=z),
        rhs_buf,
        eh_buf,
        ev_buf,
        cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(~problem.fixed, np.uint8)),
        cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.ones(rows * cols, np.uint8)),
    ]
    out = np.zeros(3)
    out_buf = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
    max_rounds = max(1, -(-int(max_sweeps) // 4))
    lsz = default_local_size(kernel, device, rows, cols) if local_size is None else int(max(1, local_size))
    kernel(
        queue,
        (lsz,),
        (lsz,),
        *bufs,
        np.int32(rows),
        np.int32(cols),
        np.int32(max_rounds),
        np.float64(tol),
        out_buf,
        cl.LocalMemory(8 * lsz),
    )
    cl.enqueue_copy(queue, z, bufs[0])
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    return SweepResult(z, int(out[0]), float(out[1]), bool(out[2]))
