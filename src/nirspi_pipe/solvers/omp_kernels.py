"""The OpenCL C source of the device OMP (:mod:`nirspi_pipe.solvers.omp_opencl` builds and runs it):
the kernels of one atom (``scatter_y``, ``mtr``, ``tm_init``, ``tm_upd``, ``pick``, ``gram``,
``tri``, ``synth``) and the whole solve in one work-group (``omp_wg``). Moved out of
:mod:`nirspi_pipe.solvers.omp_opencl` (issue 42 item 5): device code here, host code there.
"""

from __future__ import annotations

import textwrap
from string import Template

__all__ = ["KERNELS", "kernel_source"]


def _block(template: str, indent: int, **subs: str) -> str:
    """A block of kernel code written once and used twice: ``template`` with ``subs``
    filled in (``string.Template``: the C source holds no ``$``), indented by ``indent`` spaces."""
    return textwrap.indent(Template(template).substitute(subs), " " * indent).rstrip("\n")


#: The pick step: the best score and the lowest index within the tie window (two work-group
#: reductions); ``$live`` is the kernel's stop condition (empty in ``omp_wg``, whose loop stops).
_PICK = r"""double best = 0.0;
for (int e = lid; e < N$live; e += L) best = fmax(best, fabs(gb[e]) * wb[e]);
red[lid] = best;
barrier(CLK_LOCAL_MEM_FENCE);
for (int h = L / 2; h > 0; h >>= 1) {
    if (lid < h) red[lid] = fmax(red[lid], red[lid + h]);
    barrier(CLK_LOCAL_MEM_FENCE);
}
best = red[0];
const int found = ${live_found}best > 0.0;
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
"""

#: The tri step's ``w = L⁻¹ c`` (row i of L⁻¹ is column i of Lc's storage), ``‖w‖²``, ``wᵀz``, ``d²``.
_SOLVE_W = r"""double ww = 0.0, wz = 0.0;
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
"""

#: The tri step's new row of L⁻¹, ``−(wᵀ L⁻¹)/d``, and the coefficients' update; ``$live`` as in :data:`_PICK`.
_NEW_ROW = r"""for (int j = lid; j < k$live; j += L) {
    double acc = 0.0;
    for (int i = j; i < k; ++i) acc += w[i] * Lrb[i * K + j];
    const double r = acc * minv;
    Lrb[k * K + j] = r;
    Lcb[j * K + k] = r;
    sb[j] += zk * r;
}
"""

#: ``T = Mᵀ R`` in ``omp_wg`` (the kernel ``mtr``'s product, one work-item per entry in turn).
_MTR_WG = r"""for (int e = lid; e < N; e += L) {
    const int a = e / n, j = e - (e / n) * n;
    double acc = 0.0;
    for (int i = 0; i < n; ++i) acc += M[i * n + a] * Rb[i * n + j];
    Tb[e] = acc;
}
"""

#: ``T M`` in ``omp_wg`` (the kernels ``tm_init``/``tm_upd``'s product); ``$store`` writes it.
_TM_WG = r"""for (int e = lid; e < N; e += L) {
    const int a = e / n, cc = e - (e / n) * n;
    double acc = 0.0;
    for (int j = 0; j < n; ++j) acc += Tb[a * n + j] * M[j * n + cc];
$store}
"""

_SOURCE = Template(
    r"""
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
$pick_kernel
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
$solve_w_kernel
    /* d2 too small: the atom depends on the support; it is skipped (upd stays 0) */
    const int ok = !stopped && (d2 > 1e-20 * a2);
    const double d = sqrt(ok ? d2 : 1.0), minv = -1.0 / d;
    const double zk = ok ? (aty[b * N + p] - wz) / d : 0.0;
    /* new row of L^-1: -(w^T L^-1)/d, then 1/d on the diagonal */
$row_kernel
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
$mtr_wg_init
    barrier(CLK_GLOBAL_MEM_FENCE);
$tm_wg_init
    while (1) {
        barrier(CLK_GLOBAL_MEM_FENCE);
        const int stopped = s[1], k = s[0];
        barrier(CLK_GLOBAL_MEM_FENCE);
        if (stopped) break;
        /* pick */
$pick_wg
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
$solve_w_wg
        if (!(d2 > 1e-20 * a2)) continue; /* uniform: the atom is skipped */
        const double d = sqrt(d2), minv = -1.0 / d;
        const double zk = (ab[p] - wz) / d;
$row_wg
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
$mtr_wg_update
        barrier(CLK_GLOBAL_MEM_FENCE);
$tm_wg_update
    }
}
"""
).substitute(
    pick_kernel=_block(_PICK, 4, live=" && !stopped", live_found="!stopped && "),
    solve_w_kernel=_block(_SOLVE_W, 4),
    row_kernel=_block(_NEW_ROW, 4, live=" && ok"),
    mtr_wg_init=_block(_MTR_WG, 4),
    tm_wg_init=_block(_TM_WG, 4, store="    gb[e] = acc;\n    ab[e] = acc;\n"),
    pick_wg=_block(_PICK, 8, live="", live_found=""),
    solve_w_wg=_block(_SOLVE_W, 8),
    row_wg=_block(_NEW_ROW, 8, live=""),
    mtr_wg_update=_block(_MTR_WG, 8),
    tm_wg_update=_block(_TM_WG, 8, store="    gb[e] += -zk * acc;\n"),
)

KERNELS = ("scatter_y", "mtr", "tm_init", "tm_upd", "pick", "gram", "tri", "synth", "omp_wg")


def kernel_source() -> str:
    """OpenCL C source of the device OMP."""
    from nirspi_pipe.solvers.common import TIE_RTOL  # start-up: loads scipy, charset_normalizer (210 ms here)

    return _SOURCE % {"tie_rtol": float(TIE_RTOL)}
