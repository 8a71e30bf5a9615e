"""Mesh clean-up, compiled with numba: step 1 of :func:`nirspi_pipe.mesh.isotropic.clean_and_remesh_compiled`.

Numpy, then numba on the corner table of :mod:`nirspi_pipe.mesh.halfedges`:

* merge vertices with equal coordinates, drop faces with a repeated vertex or zero area,
  duplicate faces (the same three vertices in any order) and unreferenced vertices;
* orient the faces consistently per connected piece (a breadth-first walk over the edges of
  exactly two faces flips a neighbour that runs the shared edge the same way; each piece keeps
  the orientation most of its faces had), so that a closed mesh with flipped faces keeps its
  surface instead of being cut apart at every disagreeing edge below;
* pair the half-edges of each edge: an edge used by exactly two faces in opposite directions
  is interior; every other edge (one face, more than two, or two faces that disagree on the
  orientation) is cut, i.e. becomes a border of each face that uses it. The mesh is then
  edge-manifold and consistently oriented across every interior edge;
* split non-manifold vertices: a vertex whose faces form several fans (sheets touching at a
  point) gets one copy per fan;
* drop connected pieces with fewer than ``min_component_faces`` faces;
* close holes bounded by at most ``max_hole_edges`` border edges, by ear clipping (the ear
  with the smallest angle first, never creating an edge that exists already). The sheet's own
  outer border is far longer and stays open.

The same input gives the same bits on every CPU (fixed order, float64, no fast-math:
:mod:`nirspi_pipe.mesh.isotropic`).
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh.halfedges import (
    MAX_FACES,
    MAX_VALENCE,
    connected,
    find_root,
    halfedge_buckets,
    he_next,
    he_origin,
    jit_kernel,
    pair_halfedges,
    vertex_halfedges,
    vertex_ring,
)

__all__ = ["clean_mesh"]


@jit_kernel
def _orient_faces(F, nf):
    """Orient faces F[:nf] consistently per connected piece, in place: a breadth-first walk over
    the edges used by exactly two faces, from each piece's first face, flips a neighbour that
    runs the shared edge in the same direction. A piece then keeps the orientation most of its
    faces had (ties: its first face's). Edges of one face or of three and more are not crossed;
    a non-orientable piece (a Möbius strip) keeps the edges the walk could not agree on, which
    the pairing then cuts. Returns the number of faces flipped."""
    org, dst, start, out_h, out_d = halfedge_buckets(F, nf)
    flip = np.zeros(nf, np.int8)
    piece = np.full(nf, -1, np.int64)
    queue = np.empty(nf, np.int64)
    for seed in range(nf):
        if piece[seed] >= 0:
            continue
        piece[seed] = seed
        queue[0] = seed
        head, tail = 0, 1
        while head < tail:
            f = queue[head]
            head += 1
            for k in range(3):
                h = 3 * f + k
                a, b = org[h], dst[h]
                other = -1
                same = 0  # 1: the other face runs a->b too
                users = 0
                for i in range(start[a], start[a + 1]):
                    if out_d[i] == b:
                        users += 1
                        if out_h[i] != h:
                            other, same = out_h[i], 1
                for i in range(start[b], start[b + 1]):
                    if out_d[i] == a:
                        users += 1
                        other, same = out_h[i], 0
                if users != 2:
                    continue
                g = other // 3
                if piece[g] < 0:
                    piece[g] = seed
                    flip[g] = flip[f] ^ same
                    queue[tail] = g
                    tail += 1
    # each piece keeps the orientation most of its faces had
    flipped = np.zeros(nf, np.int64)
    size = np.zeros(nf, np.int64)
    for f in range(nf):
        size[piece[f]] += 1
        flipped[piece[f]] += flip[f]
    n_flipped = 0
    for f in range(nf):
        if 2 * flipped[piece[f]] > size[piece[f]]:
            flip[f] ^= 1
        if flip[f]:
            F[f, 1], F[f, 2] = F[f, 2], F[f, 1]
            n_flipped += 1
    return n_flipped


@jit_kernel
def _split_fans(F, opp, nv):
    """Give every fan of a non-manifold vertex its own vertex. Returns (F', source vertex of
    each vertex of F')."""
    nf = F.shape[0]
    m = 3 * nf
    parent = np.arange(m)
    # corner c (at vertex v) and the corner at v across the edge leaving v belong to one fan
    for c in range(m):
        o = opp[c]
        if o >= 0:
            # o runs dst(c) -> v; the corner at v in o's face is next(o)
            a, b = find_root(parent, c), find_root(parent, he_next(o))
            if a != b:
                parent[max(a, b)] = min(a, b)
    root_vertex = np.full(m, -1, np.int64)
    first_root = np.full(nv, -1, np.int64)
    src = np.empty(nv + m, np.int64)
    for v in range(nv):
        src[v] = v
    n_out = nv
    G = F.copy()
    for c in range(m):
        r = find_root(parent, c)
        v = F[c // 3, c % 3]
        if root_vertex[r] < 0:
            if first_root[v] < 0:
                first_root[v] = r
                root_vertex[r] = v
            else:
                root_vertex[r] = n_out
                src[n_out] = v
                n_out += 1
        G[c // 3, c % 3] = root_vertex[r]
    return G, src[:n_out].copy()


@jit_kernel
def _components(opp, nf):
    """Connected piece of each face (connectivity across paired edges)."""
    parent = np.arange(nf)
    for h in range(3 * nf):
        o = opp[h]
        if o >= 0:
            a, b = find_root(parent, h // 3), find_root(parent, o // 3)
            if a != b:
                parent[max(a, b)] = min(a, b)
    for f in range(nf):
        parent[f] = find_root(parent, f)
    return parent


@jit_kernel
def _min_angle_cos(V, a, b, c):
    """Cosine of the smallest angle of triangle (a, b, c): 1 when it has no area."""
    worst = -1.0
    for i in range(3):
        p, q, r = (a, b, c) if i == 0 else ((b, c, a) if i == 1 else (c, a, b))
        u0, u1, u2 = V[q, 0] - V[p, 0], V[q, 1] - V[p, 1], V[q, 2] - V[p, 2]
        w0, w1, w2 = V[r, 0] - V[p, 0], V[r, 1] - V[p, 1], V[r, 2] - V[p, 2]
        nu = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        nw = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        if nu == 0.0 or nw == 0.0:
            return 1.0
        worst = max(worst, (u0 * w0 + u1 * w1 + u2 * w2) / (nu * nw))
    return worst


@jit_kernel
def _face_exists(F, opp, vh, a, b, c, buf):
    """True when some face has the vertices a, b and c."""
    n, _ = vertex_ring(F, opp, vh, a, buf)
    for i in range(n):
        g = buf[i] // 3
        has_b = F[g, 0] == b or F[g, 1] == b or F[g, 2] == b
        has_c = F[g, 0] == c or F[g, 1] == c or F[g, 2] == c
        if has_b and has_c:
            return True
    return False


@jit_kernel
def _walk_border(F, opp, h0, seen, loop, max_edges):
    """Walk the border loop from the border half-edge h0 (a->b; the next border half-edge leaves
    b), marking its half-edges seen and keeping its first max_edges + 1 vertices in loop: its
    length, or -1 when the walk meets a vertex whose fan it cannot get round."""
    nf = F.shape[0]
    n = 0
    h = h0
    for _ in range(3 * nf):
        seen[h] = True
        if n <= max_edges:
            loop[n] = he_origin(F, h)
        n += 1
        g = he_next(h)
        steps = 0
        while opp[g] >= 0 and steps < MAX_VALENCE:
            g = he_next(opp[g])
            steps += 1
        if opp[g] >= 0:
            return -1
        h = g
        if h == h0:
            break
    return n


@jit_kernel
def _best_ear(V, F, opp, vh, loop, cnt, new, start_new, n_new, buf):
    """The ear (index in loop[:cnt]) whose smallest angle is the largest, among those that make
    no existing edge and no edge the fill already made; -1 when there is none."""
    best = -1
    best_cos = 1.0 - 1e-12  # a zero-area ear (cosine 1) is never taken
    for i in range(cnt):
        a, b, c = loop[(i - 1) % cnt], loop[i], loop[(i + 1) % cnt]
        if a == c or connected(F, opp, vh, a, c, buf):
            continue
        dup = False
        for k in range(start_new, n_new):  # an edge the fill already made
            if (new[k, 0] == a or new[k, 1] == a or new[k, 2] == a) and (
                new[k, 0] == c or new[k, 1] == c or new[k, 2] == c
            ):
                dup = True
                break
        if dup:
            continue
        q = _min_angle_cos(V, a, b, c)
        if q < best_cos:  # the ear whose smallest angle is the largest
            best_cos = q
            best = i
    return best


@jit_kernel
def _close_holes(V, F, opp, nv, max_edges):
    """Faces closing every border loop of at most max_edges edges, by ear clipping: (new faces
    (k, 3), number of loops left open)."""
    nf = F.shape[0]
    vh = vertex_halfedges(F, nf, nv)
    seen = np.zeros(3 * nf, np.bool_)
    new = np.empty((max(16, 3 * nf), 3), np.int64)
    n_new = 0
    n_open = 0
    loop = np.empty(max_edges + 2, np.int64)
    buf = np.empty(2 * MAX_VALENCE + 2, np.int64)
    for h0 in range(3 * nf):
        if opp[h0] >= 0 or seen[h0]:
            continue
        n = _walk_border(F, opp, h0, seen, loop, max_edges)
        if n < 0 or n > max_edges or n < 3:
            continue
        # the loop runs along the existing faces (their border half-edges v_i -> v_i+1); the
        # ear at v_i is the face (v_i+1, v_i, v_i-1), which pairs with both border half-edges
        cnt = n
        start_new = n_new
        while cnt > 3:
            best = _best_ear(V, F, opp, vh, loop, cnt, new, start_new, n_new, buf)
            if best < 0:
                break
            a, b, c = loop[(best - 1) % cnt], loop[best], loop[(best + 1) % cnt]
            new[n_new, 0], new[n_new, 1], new[n_new, 2] = c, b, a
            n_new += 1
            for k in range(best, cnt - 1):
                loop[k] = loop[k + 1]
            cnt -= 1
        if cnt == 3 and not _face_exists(F, opp, vh, loop[0], loop[1], loop[2], buf):
            new[n_new, 0], new[n_new, 1], new[n_new, 2] = loop[2], loop[1], loop[0]
            n_new += 1
        else:  # no ear left, or the last one is a face already (a lone triangle's own border)
            n_new = start_new  # give up on this hole
            n_open += 1
    return new[:n_new].copy(), n_open


def clean_mesh(
    vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int = 30, min_component_faces: int = 10
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """The clean-up of the module docstring: ``(vertices, faces, info)``, same units in and out.
    The result is edge-manifold, vertex-manifold and consistently oriented across every edge
    shared by two faces."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    info: dict[str, float] = {}
    if len(f) == 0:
        return v[:0], f, info
    if len(f) > MAX_FACES:
        raise NirspiError(f"mesh clean-up: {len(f)} faces, more than the {MAX_FACES} this remesher takes")
    if f.min() < 0 or f.max() >= len(v):
        raise NirspiError(f"mesh clean-up: face indices outside 0..{len(v) - 1}")
    if not np.all(np.isfinite(v)):
        raise NirspiError("mesh clean-up: non-finite vertex coordinates")
    # merge vertices with equal coordinates (a stable lexicographic sort, then runs)
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    sv = v[order]
    new = np.ones(len(v), dtype=bool)
    new[1:] = np.any(sv[1:] != sv[:-1], axis=1)
    rank = np.cumsum(new) - 1
    inv = np.empty(len(v), dtype=np.int64)
    inv[order] = rank
    uv = sv[new]
    f = inv[f]
    # faces with a repeated vertex or zero area, then duplicate faces (any order)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    p = uv[f]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    cr = np.stack(
        [
            e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
            e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
            e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0],
        ],
        axis=1,
    )
    f = f[np.any(cr != 0.0, axis=1)]
    sf = np.sort(f, axis=1)
    n = len(uv)
    if n < 2_000_000:  # n**3 fits an int64: one key per face
        _, first = np.unique((sf[:, 0] * n + sf[:, 1]) * n + sf[:, 2], return_index=True)
    else:
        _, first = np.unique(sf, axis=0, return_index=True)
    f = f[np.sort(first)]
    info["faces_dropped_degenerate"] = int(len(faces) - len(f))
    if len(f) == 0:
        return uv[:0], f, info
    f = np.ascontiguousarray(f)
    info["faces_flipped"] = int(_orient_faces(f, len(f)))  # consistent orientation first (in place)
    opp = pair_halfedges(f, len(f))
    f, src = _split_fans(f, opp, len(uv))
    uv = uv[src]
    if min_component_faces > 0:
        comp = _components(opp, len(f))  # each face's piece, named by its smallest face
        small = np.bincount(comp, minlength=len(f))[comp] < min_component_faces
        info["faces_in_small_pieces"] = int(small.sum())
        f = f[~small]
        opp = pair_halfedges(f, len(f)) if small.any() else opp
    if max_hole_edges > 0 and len(f):
        new, n_open = _close_holes(uv, f, opp, len(uv), int(max_hole_edges))
        info["holes_not_closed"] = int(n_open)
        info["faces_hole_fill"] = int(len(new))
        if len(new):
            f = np.vstack([f, new])
    used = np.zeros(len(uv), dtype=bool)
    used[f] = True
    new_id = np.cumsum(used) - 1
    return uv[used], new_id[f], info
