"""The compiled remesher's triangle geometry and its edge flips (:mod:`nirspi_pipe.mesh.isotropic`).

``face_normal`` and ``len2`` (a face's normal, an edge's squared length) serve the splits, collapses
and relaxation of the remesher too; ``flip_edges`` is its third step (Botsch & Kobbelt 2004):
flipping interior edges that bring the four vertices' valences closer to 6 (4 on the border),
unless a face would turn over or its shape degrade. Compiled like the rest of the remesher, on
float64 without fast-math (the same bits with and without FMA: tests/test_mesh_remesh_compiled.py).
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.mesh.halfedges import (
    connected,
    he_next,
    he_prev,
    he_target,
    jit_inline,
    jit_kernel,
)

__all__ = ["face_normal", "flip_edges", "len2"]


@jit_inline
def face_normal(V, a, b, c, out):
    u0, u1, u2 = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
    w0, w1, w2 = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
    out[0] = u1 * w2 - u2 * w1
    out[1] = u2 * w0 - u0 * w2
    out[2] = u0 * w1 - u1 * w0


@jit_inline
def len2(V, a, b):
    d0, d1, d2 = V[a, 0] - V[b, 0], V[a, 1] - V[b, 1], V[a, 2] - V[b, 2]
    return d0 * d0 + d1 * d1 + d2 * d2


@jit_inline
def _shape(V, a, b, c):
    """4√3·area / (sum of squared edge lengths): 1 for an equilateral triangle, 0 for a degenerate one."""
    u0, u1, u2 = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
    w0, w1, w2 = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
    x, y, z = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
    e = (u0 * u0 + u1 * u1 + u2 * u2) + (w0 * w0 + w1 * w1 + w2 * w2) + len2(V, b, c)
    return 2.0 * np.sqrt(3.0) * np.sqrt(x * x + y * y + z * z) / e if e > 0.0 else 0.0


@jit_kernel
def _valences(F, bnd, nf, nv):
    """Number of neighbours of each vertex: its faces, plus one on a border."""
    val = np.zeros(nv, np.int64)
    for f in range(nf):
        if F[f, 0] >= 0:
            for k in range(3):
                val[F[f, k]] += 1
    for v in range(nv):
        if bnd[v]:
            val[v] += 1
    return val


@jit_kernel
def _flip_helps(val, bnd, a, b, c, d):
    """Whether flipping edge a-b (to c-d) brings the four valences closer to 6 (4 on a border),
    leaving a and b at least 3 faces (2 on a border)."""
    va, vb, vc, vd = val[a], val[b], val[c], val[d]
    ta, tb, tc, td = 4 if bnd[a] else 6, 4 if bnd[b] else 6, 4 if bnd[c] else 6, 4 if bnd[d] else 6
    if va <= (2 if bnd[a] else 3) or vb <= (2 if bnd[b] else 3):
        return False
    before = (va - ta) ** 2 + (vb - tb) ** 2 + (vc - tc) ** 2 + (vd - td) ** 2
    after = (va - 1 - ta) ** 2 + (vb - 1 - tb) ** 2 + (vc + 1 - tc) ** 2 + (vd + 1 - td) ** 2
    return after < before


@jit_kernel
def _flip_keeps_shape(V, a, b, c, d, nrm, nrm2):
    """Whether the new faces (c, a, d) and (d, b, c) face the way the old ones (a, b, c) and
    (b, a, d) did, and the worse of them keeps at least half the old worse face's shape quality."""
    # the two new faces (c, a, d) and (d, b, c) must face the way the old ones did
    face_normal(V, a, b, c, nrm)
    face_normal(V, b, a, d, nrm2)
    sx, sy, sz = nrm[0] + nrm2[0], nrm[1] + nrm2[1], nrm[2] + nrm2[2]
    face_normal(V, c, a, d, nrm)
    face_normal(V, d, b, c, nrm2)
    n1 = nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]
    n2 = nrm2[0] * nrm2[0] + nrm2[1] * nrm2[1] + nrm2[2] * nrm2[2]
    s2 = sx * sx + sy * sy + sz * sz
    d1 = nrm[0] * sx + nrm[1] * sy + nrm[2] * sz
    d2 = nrm2[0] * sx + nrm2[1] * sy + nrm2[2] * sz
    if d1 <= 0.0 or d2 <= 0.0 or d1 * d1 < 0.25 * n1 * s2 or d2 * d2 < 0.25 * n2 * s2:
        return False
    # nor may the worse of the two faces lose more than half its shape quality (a
    # valence-driven flip across a flat, skinny quad would make a needle)
    q_old = min(_shape(V, a, b, c), _shape(V, b, a, d))
    return not min(_shape(V, c, a, d), _shape(V, d, b, c)) < 0.5 * q_old


@jit_kernel
def _flip(F, opp, vh, val, f, h, o, a, b, c, d):
    """Flip edge a-b of face f (half-edge h, its twin o): faces (c, a, d) and (d, b, c), the
    twins, vertex half-edges and valences updated."""
    g = o // 3
    x_bc, x_ca = opp[he_next(h)], opp[he_prev(h)]
    x_ad, x_db = opp[he_next(o)], opp[he_prev(o)]
    F[f, 0], F[f, 1], F[f, 2] = c, a, d
    F[g, 0], F[g, 1], F[g, 2] = d, b, c
    pairs = ((3 * f, x_ca), (3 * f + 1, x_ad), (3 * g, x_db), (3 * g + 1, x_bc))
    for e, x in pairs:
        opp[e] = x
        if x >= 0:
            opp[x] = e
    opp[3 * f + 2] = 3 * g + 2
    opp[3 * g + 2] = 3 * f + 2
    vh[a], vh[b], vh[c], vh[d] = 3 * f + 1, 3 * g + 1, 3 * f, 3 * g
    val[a] -= 1
    val[b] -= 1
    val[c] += 1
    val[d] += 1


@jit_kernel
def flip_edges(V, F, opp, vh, bnd, nf, nv, buf, nrm, nrm2):
    """Flip interior edges that bring the valences closer to 6 (4 on a border)."""
    count = 0
    val = _valences(F, bnd, nf, nv)
    for f in range(nf):
        if F[f, 0] < 0:
            continue
        for k in range(3):
            h = 3 * f + k
            o = opp[h]
            if o < h:  # border (-1) or visited from the other side
                continue
            a, b = F[f, k], F[f, (k + 1) % 3]
            c = he_target(F, he_next(h))
            d = he_target(F, he_next(o))
            if c == d or not _flip_helps(val, bnd, a, b, c, d):
                continue
            if not _flip_keeps_shape(V, a, b, c, d, nrm, nrm2):
                continue
            if connected(F, opp, vh, c, d, buf):
                continue
            _flip(F, opp, vh, val, f, h, o, a, b, c, d)
            count += 1
            break  # face f changed: its other edges are visited in the next round
    return count
