"""The corner table (half-edges) the compiled mesh kernels share, and their numba decorators.

Used by the clean-up (:mod:`nirspi_pipe.mesh.meshclean`), the isotropic remesher
(:mod:`nirspi_pipe.mesh.isotropic`) and the power crust's faces (:mod:`nirspi_pipe.mesh.crustfaces`).
Face f has corners 3f, 3f+1, 3f+2; corner c holds vertex F[f, c % 3] and is the start of the
half-edge from that vertex to the next corner's. opp[h] is the opposite half-edge (-1 on a border
or a cut edge); vh[v] is some live half-edge leaving v (-1: v is unused).

:func:`jit_kernel` compiles a kernel with numba and caches it in the private folder of
:mod:`nirspi_pipe.mesh.jitcache`; fixed order, float64, no fast-math, so the same input gives the
same bits on every CPU (:mod:`nirspi_pipe.mesh.isotropic`). Without numba the kernels run as
plain Python (:data:`HAVE_NUMBA` is then False and the surface stages fall back to pymeshlab).
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.mesh import jitcache

__all__ = [
    "HAVE_NUMBA",
    "MAX_FACES",
    "MAX_VALENCE",
    "jit_kernel",
    "jit_inline",
    "he_next",
    "he_prev",
    "he_origin",
    "he_target",
    "halfedge_buckets",
    "pair_halfedges",
    "find_root",
    "vertex_halfedges",
    "vertex_ring",
    "border_flags",
    "connected",
    "ranks",
    "live_faces",
]

#: Largest mesh (faces, before or after remeshing) the clean-up and the remesher will build.
#: Assumed: 2 million, a thousand times the 3D path's meshes (~2 000 faces at 32²). The
#: remesher's working arrays take 81 bytes per face of room (faces 24, their opposite half-edges
#: 24, vertices 24 + 8 + 1), and the room never exceeds twice this limit: at most ~330 MB. Beyond
#: it the input is refused with a one-line error.
MAX_FACES = 2_000_000
MAX_VALENCE = 4096  # bound on a vertex's ring walk: a corrupted table cannot loop forever

try:  # numba ships with miepython (a core dependency); the surface stages fall back to pymeshlab
    from numba import njit
except ImportError:  # pragma: no cover - exercised only where numba is absent
    njit = None  # type: ignore[assignment]

#: True when numba is installed (the kernels are compiled); False: they are plain Python.
HAVE_NUMBA = njit is not None


def jit_kernel(fn):
    """Compiled, cached in the private folder of :mod:`nirspi_pipe.mesh.jitcache`."""
    return jitcache.jit(fn) if njit is not None else fn


def jit_inline(fn):
    """For the one-line corner-table helpers: inlined into their callers (numba otherwise calls
    them as functions)."""
    return jitcache.jit(fn, inline="always") if njit is not None else fn


@jit_inline
def he_next(h):
    return h - h % 3 + (h % 3 + 1) % 3


@jit_inline
def he_prev(h):
    return h - h % 3 + (h % 3 + 2) % 3


@jit_inline
def he_origin(F, h):
    return F[h // 3, h % 3]


@jit_inline
def he_target(F, h):
    return F[h // 3, (h % 3 + 1) % 3]


@jit_kernel
def halfedge_buckets(F, nf):
    """Half-edges of faces F[:nf] bucketed by origin (counting sort): (org, dst, start, out_h,
    out_d); the half-edges leaving v are out_h[start[v]:start[v + 1]], ending at out_d[…]."""
    m = 3 * nf
    org = np.empty(m, np.int64)
    dst = np.empty(m, np.int64)
    nv = 0
    for f in range(nf):
        for k in range(3):
            org[3 * f + k] = F[f, k]
            dst[3 * f + k] = F[f, (k + 1) % 3]
            nv = max(nv, F[f, k] + 1)
    start = np.zeros(nv + 1, np.int64)
    for h in range(m):
        start[org[h] + 1] += 1
    for v in range(nv):
        start[v + 1] += start[v]
    fill = start[:nv].copy()
    out_h = np.empty(m, np.int64)
    out_d = np.empty(m, np.int64)
    for h in range(m):
        a = org[h]
        out_h[fill[a]] = h
        out_d[fill[a]] = dst[h]
        fill[a] += 1
    return org, dst, start, out_h, out_d


@jit_kernel
def pair_halfedges(F, nf):
    """opp for faces F[:nf]: half-edges a->b and b->a of an edge used by exactly these two.
    Half-edges are bucketed by origin (:func:`halfedge_buckets`), so each pairing looks at one
    vertex's few outgoing half-edges."""
    m = 3 * nf
    org, dst, start, out_h, out_d = halfedge_buckets(F, nf)
    opp = np.full(m, -1, np.int64)
    for h in range(m):
        a, b = org[h], dst[h]
        same = 0
        for i in range(start[a], start[a + 1]):
            if out_d[i] == b:
                same += 1
        if same != 1:
            continue
        back = -1
        n_back = 0
        for i in range(start[b], start[b + 1]):
            if out_d[i] == a:
                back = out_h[i]
                n_back += 1
        if n_back == 1:
            opp[h] = back
    return opp


@jit_kernel
def find_root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@jit_kernel
def vertex_halfedges(F, nf, nv):
    vh = np.full(nv, -1, np.int64)
    for h in range(3 * nf):
        v = F[h // 3, h % 3]
        if v >= 0 and vh[v] < 0:
            vh[v] = h
    return vh


@jit_kernel
def vertex_ring(F, opp, vh, v, out):
    """Outgoing half-edges of v into out; returns (count, on_border). Walks one way around the
    fan, then, if it met a border, the other way from the start."""
    h0 = vh[v]
    if h0 < 0:
        return 0, False
    n = 0
    out[n] = h0
    n += 1
    h = h0
    border = False
    for _ in range(MAX_VALENCE):
        o = opp[he_prev(h)]
        if o < 0:
            border = True
            break
        if o == h0:
            return n, False
        out[n] = o
        n += 1
        h = o
    if not border:
        return n, False
    h = h0
    for _ in range(MAX_VALENCE):
        o = opp[h]
        if o < 0:
            break
        h = he_next(o)
        out[n] = h
        n += 1
    return n, True


@jit_kernel
def border_flags(F, opp, vh, nv):
    bnd = np.zeros(nv, np.bool_)
    buf = np.empty(2 * MAX_VALENCE + 2, np.int64)
    for v in range(nv):
        if vh[v] >= 0:
            _, b = vertex_ring(F, opp, vh, v, buf)
            bnd[v] = b
    return bnd


@jit_kernel
def connected(F, opp, vh, a, b, buf):
    n, _ = vertex_ring(F, opp, vh, a, buf)
    for i in range(n):
        if he_target(F, buf[i]) == b:
            return True
    # on a border the last neighbour is reached only as the origin of an incoming half-edge
    for i in range(n):
        if he_origin(F, he_prev(buf[i])) == b:
            return True
    return False


@jit_kernel
def ranks(used):
    """Each marked index's rank among the marked ones (-1 for the others), and their count."""
    rank = np.full(used.shape[0], -1, np.int64)
    n = 0
    for i in range(used.shape[0]):
        if used[i]:
            rank[i] = n
            n += 1
    return rank, n


@jit_kernel
def live_faces(F, nv):
    """The live faces of F (first index >= 0) renumbered into the vertices they use, and those
    vertices' old indices (ascending)."""
    used = np.zeros(nv, np.bool_)
    n_f = 0
    for f in range(F.shape[0]):
        if F[f, 0] >= 0:
            n_f += 1
            for k in range(3):
                used[F[f, k]] = True
    new_id, n = ranks(used)
    keep = np.empty(n, np.int64)
    for v in range(nv):
        if used[v]:
            keep[new_id[v]] = v
    out = np.empty((n_f, 3), np.int64)
    n_f = 0
    for f in range(F.shape[0]):
        if F[f, 0] >= 0:
            for k in range(3):
                out[n_f, k] = new_id[F[f, k]]
            n_f += 1
    return keep, out
