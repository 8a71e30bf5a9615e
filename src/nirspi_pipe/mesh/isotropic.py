"""Mesh clean-up and isotropic remeshing, compiled with numba (``remesher: compiled``).

The same two steps as :func:`nirspi_pipe.mesh.remesh.clean_and_remesh` (pymeshlab), for the small
meshes of the 3D path (a few thousand faces). On the power crusts of the 16 jobs of ``nirspi-run -m
+experiment=table6 illumination.klux=5 seed=0``, welded as the stage welds them, pymeshlab's clean-up
and remeshing took 31.9 ms per mesh and the compiled ones below 1.7 + 4.4 ms (medians,
``experiments/mesh/remesher_timing.py``); ``nirspi-bench mesh3d`` prints both, measured in the
same run.

1. **Clean-up** (numpy, then numba on a corner table):

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

2. **Isotropic remeshing** (Botsch & Kobbelt, "A remeshing approach to multiresolution modeling",
   SGP 2004): ``iterations`` rounds of

   * splitting every edge longer than 4/3 L at its midpoint,
   * collapsing every edge shorter than 4/5 L (when the link condition holds, no edge longer than
     4/3 L appears, no face turns over, and no border would be pinched; a border vertex stays on
     the border, and a border edge only collapses along the border),
   * flipping interior edges that bring the four vertices' valences closer to 6 (4 on the
     border), unless a face would turn over,
   * tangential relaxation: each interior vertex moves to the mean of its neighbours, projected
     onto its tangent plane (the area-weighted normal), so the surface stays where it was to
     second order. Border vertices stay fixed.

   ``L`` is the target edge length. Unlike pymeshlab's filter there is no feature-edge detection
   and no reprojection onto the input surface (the Table 6 jobs' chamfer distance to the true
   surface: 5.64 mm with this remesher, 5.70 mm with pymeshlab's; docs/mesh.md).

Everything runs in a fixed order on float64 without fast-math: numba compiles for the host CPU,
but without ``fastmath`` LLVM may neither reorder floating-point operations nor fuse a multiply
and an add (tests/test_mesh_remesh_compiled.py finds no fused multiply-add instruction in the
compiled kernels), so the same input gives the same bits on CPUs with and without FMA or AVX-512. Compiled code is cached on disk (numba's ``cache=True``);
:func:`warm_up` compiles or loads it when a surface stage is built, so compilation is never part
of a stage's time.
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh import jitcache

__all__ = ["clean_and_remesh_compiled", "warm_up", "clean_mesh", "MAX_FACES"]

#: Largest mesh (faces, before or after remeshing) this module will build. Assumed: 2 million, a
#: thousand times the 3D path's meshes (~2 000 faces at 32²). The remesher's working arrays take
#: 81 bytes per face of room (faces 24, their opposite half-edges 24, vertices 24 + 8 + 1), and
#: the room never exceeds twice this limit: at most ~330 MB. Beyond it the input is refused
#: with a one-line error.
MAX_FACES = 2_000_000

_PASSES = 1  # collapse and flip passes per iteration (Botsch & Kobbelt: one)
_MAX_VALENCE = 4096  # bound on a vertex's ring walk: a corrupted table cannot loop forever

try:  # numba ships with miepython (a core dependency); the surface stages fall back to pymeshlab
    from numba import njit
except ImportError:  # pragma: no cover - exercised only where numba is absent
    njit = None  # type: ignore[assignment]


def _jit(fn):
    """Compiled, cached in the private folder of :mod:`nirspi_pipe.mesh.jitcache`."""
    return jitcache.jit(fn) if njit is not None else fn


def _jit_inline(fn):
    """For the one-line corner-table helpers: inlined into their callers (numba otherwise calls
    them as functions)."""
    return jitcache.jit(fn, inline="always") if njit is not None else fn


# ---------------------------------------------------------------------------------------------
# corner table: face f has corners 3f, 3f+1, 3f+2; corner c holds vertex F[f, c % 3] and is the
# start of the half-edge from that vertex to the next corner's. opp[h] is the opposite half-edge
# (-1 on a border or a cut edge); vh[v] is some live half-edge leaving v (-1: v is unused).
# ---------------------------------------------------------------------------------------------


@_jit_inline
def _nxt(h):
    return h - h % 3 + (h % 3 + 1) % 3


@_jit_inline
def _prv(h):
    return h - h % 3 + (h % 3 + 2) % 3


@_jit_inline
def _org(F, h):
    return F[h // 3, h % 3]


@_jit_inline
def _dst(F, h):
    return F[h // 3, (h % 3 + 1) % 3]


@_jit
def _halfedge_buckets(F, nf):
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


@_jit
def _pair_halfedges(F, nf):
    """opp for faces F[:nf]: half-edges a->b and b->a of an edge used by exactly these two.
    Half-edges are bucketed by origin (:func:`_halfedge_buckets`), so each pairing looks at one
    vertex's few outgoing half-edges."""
    m = 3 * nf
    org, dst, start, out_h, out_d = _halfedge_buckets(F, nf)
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


@_jit
def _orient_faces(F, nf):
    """Orient faces F[:nf] consistently per connected piece, in place: a breadth-first walk over
    the edges used by exactly two faces, from each piece's first face, flips a neighbour that
    runs the shared edge in the same direction. A piece then keeps the orientation most of its
    faces had (ties: its first face's). Edges of one face or of three and more are not crossed;
    a non-orientable piece (a Möbius strip) keeps the edges the walk could not agree on, which
    the pairing then cuts. Returns the number of faces flipped."""
    org, dst, start, out_h, out_d = _halfedge_buckets(F, nf)
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


@_jit
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@_jit
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
            a, b = _find(parent, c), _find(parent, _nxt(o))
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
        r = _find(parent, c)
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


@_jit
def _components(opp, nf):
    """Connected piece of each face (connectivity across paired edges)."""
    parent = np.arange(nf)
    for h in range(3 * nf):
        o = opp[h]
        if o >= 0:
            a, b = _find(parent, h // 3), _find(parent, o // 3)
            if a != b:
                parent[max(a, b)] = min(a, b)
    for f in range(nf):
        parent[f] = _find(parent, f)
    return parent


@_jit
def _vertex_halfedges(F, nf, nv):
    vh = np.full(nv, -1, np.int64)
    for h in range(3 * nf):
        v = F[h // 3, h % 3]
        if v >= 0 and vh[v] < 0:
            vh[v] = h
    return vh


@_jit
def _ring(F, opp, vh, v, out):
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
    for _ in range(_MAX_VALENCE):
        o = opp[_prv(h)]
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
    for _ in range(_MAX_VALENCE):
        o = opp[h]
        if o < 0:
            break
        h = _nxt(o)
        out[n] = h
        n += 1
    return n, True


@_jit
def _border_flags(F, opp, vh, nv):
    bnd = np.zeros(nv, np.bool_)
    buf = np.empty(2 * _MAX_VALENCE + 2, np.int64)
    for v in range(nv):
        if vh[v] >= 0:
            _, b = _ring(F, opp, vh, v, buf)
            bnd[v] = b
    return bnd


@_jit
def _connected(F, opp, vh, a, b, buf):
    n, _ = _ring(F, opp, vh, a, buf)
    for i in range(n):
        if _dst(F, buf[i]) == b:
            return True
    # on a border the last neighbour is reached only as the origin of an incoming half-edge
    for i in range(n):
        if _org(F, _prv(buf[i])) == b:
            return True
    return False


@_jit
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


@_jit
def _face_exists(F, opp, vh, a, b, c, buf):
    """True when some face has the vertices a, b and c."""
    n, _ = _ring(F, opp, vh, a, buf)
    for i in range(n):
        g = buf[i] // 3
        has_b = F[g, 0] == b or F[g, 1] == b or F[g, 2] == b
        has_c = F[g, 0] == c or F[g, 1] == c or F[g, 2] == c
        if has_b and has_c:
            return True
    return False


@_jit
def _close_holes(V, F, opp, nv, max_edges):
    """Faces closing every border loop of at most max_edges edges, by ear clipping: (new faces
    (k, 3), number of loops left open)."""
    nf = F.shape[0]
    vh = _vertex_halfedges(F, nf, nv)
    seen = np.zeros(3 * nf, np.bool_)
    new = np.empty((max(16, 3 * nf), 3), np.int64)
    n_new = 0
    n_open = 0
    loop = np.empty(max_edges + 2, np.int64)
    buf = np.empty(2 * _MAX_VALENCE + 2, np.int64)
    for h0 in range(3 * nf):
        if opp[h0] >= 0 or seen[h0]:
            continue
        # walk the loop: from the border half-edge a->b, the next border half-edge leaves b
        n = 0
        h = h0
        ok = True
        for _ in range(3 * nf):
            seen[h] = True
            if n <= max_edges:
                loop[n] = _org(F, h)
            n += 1
            g = _nxt(h)
            steps = 0
            while opp[g] >= 0 and steps < _MAX_VALENCE:
                g = _nxt(opp[g])
                steps += 1
            if opp[g] >= 0:
                ok = False
                break
            h = g
            if h == h0:
                break
        if not ok or n > max_edges or n < 3:
            continue
        # the loop runs along the existing faces (their border half-edges v_i -> v_i+1); the
        # ear at v_i is the face (v_i+1, v_i, v_i-1), which pairs with both border half-edges
        cnt = n
        start_new = n_new
        while cnt > 3:
            best = -1
            best_cos = 1.0 - 1e-12  # a zero-area ear (cosine 1) is never taken
            for i in range(cnt):
                a, b, c = loop[(i - 1) % cnt], loop[i], loop[(i + 1) % cnt]
                if a == c or _connected(F, opp, vh, a, c, buf):
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
    opp = _pair_halfedges(f, len(f))
    f, src = _split_fans(f, opp, len(uv))
    uv = uv[src]
    if min_component_faces > 0:
        comp = _components(opp, len(f))  # each face's piece, named by its smallest face
        small = np.bincount(comp, minlength=len(f))[comp] < min_component_faces
        info["faces_in_small_pieces"] = int(small.sum())
        f = f[~small]
        opp = _pair_halfedges(f, len(f)) if small.any() else opp
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


# ---------------------------------------------------------------------------------------------
# remeshing
# ---------------------------------------------------------------------------------------------


@_jit_inline
def _face_normal(V, a, b, c, out):
    u0, u1, u2 = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
    w0, w1, w2 = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
    out[0] = u1 * w2 - u2 * w1
    out[1] = u2 * w0 - u0 * w2
    out[2] = u0 * w1 - u1 * w0


@_jit_inline
def _len2(V, a, b):
    d0, d1, d2 = V[a, 0] - V[b, 0], V[a, 1] - V[b, 1], V[a, 2] - V[b, 2]
    return d0 * d0 + d1 * d1 + d2 * d2


@_jit
def _split_long(V, F, opp, vh, bnd, nv, nf, hi2):
    """Split every edge longer than sqrt(hi2) at its midpoint (new faces are visited too; passes
    repeat until none is left). Returns (nv, nf, overflow)."""
    for _pass in range(16):
        nf0 = nf
        nv, nf, overflow = _split_pass(V, F, opp, vh, bnd, nv, nf, hi2)
        if overflow or nf == nf0:
            return nv, nf, overflow
    return nv, nf, False


@_jit
def _split_pass(V, F, opp, vh, bnd, nv, nf, hi2):
    f = 0
    while f < nf:
        if F[f, 0] < 0:
            f += 1
            continue
        did = False
        for k in range(3):
            h = 3 * f + k
            a, b = F[f, k], F[f, (k + 1) % 3]
            o = opp[h]
            if o >= 0 and o < h:
                continue  # each interior edge once, from its lower half-edge
            if _len2(V, a, b) <= hi2:
                continue
            # only when the split shortens: the new edges to the opposite vertices must be shorter
            # than this one (not so in a degenerate, needle-like triangle, which flips handle)
            l2 = _len2(V, a, b)
            c = F[f, (k + 2) % 3]
            mx, my, mz = 0.5 * (V[a, 0] + V[b, 0]), 0.5 * (V[a, 1] + V[b, 1]), 0.5 * (V[a, 2] + V[b, 2])
            if (mx - V[c, 0]) ** 2 + (my - V[c, 1]) ** 2 + (mz - V[c, 2]) ** 2 >= l2:
                continue
            if o >= 0:
                e = _dst(F, _nxt(o))
                if (mx - V[e, 0]) ** 2 + (my - V[e, 1]) ** 2 + (mz - V[e, 2]) ** 2 >= l2:
                    continue
            if nv + 1 > V.shape[0] or nf + 2 > F.shape[0]:
                return nv, nf, True
            m = nv
            nv += 1
            V[m, 0], V[m, 1], V[m, 2] = mx, my, mz
            bnd[m] = o < 0
            # face f = (a, b, c) -> (a, m, c) and new face g = (m, b, c)
            hn = _nxt(h)
            x = opp[hn]
            g = nf
            nf += 1
            F[g, 0], F[g, 1], F[g, 2] = m, b, c
            F[f, (k + 1) % 3] = m
            opp[3 * g + 2] = hn  # c->m pairs with m->c (hn now starts at m)
            opp[hn] = 3 * g + 2
            opp[3 * g + 1] = x  # b->c keeps the old neighbour
            if x >= 0:
                opp[x] = 3 * g + 1
            vh[m] = 3 * g
            vh[b] = 3 * g + 1
            vh[c] = 3 * g + 2 if vh[c] < 0 else vh[c]
            if o >= 0:
                # face f1 = (b, a, d) with o = b->a -> (m, a, d) and new face g1 = (b, m, d)
                f1 = o // 3
                j = o % 3
                d_ = F[f1, (j + 2) % 3]
                op = _prv(o)  # d->b, becomes d->m
                y = opp[op]
                g1 = nf
                nf += 1
                F[g1, 0], F[g1, 1], F[g1, 2] = b, m, d_
                F[f1, j] = m
                opp[3 * g1 + 1] = op  # m->d pairs with d->m
                opp[op] = 3 * g1 + 1
                opp[3 * g1 + 2] = y  # d->b keeps the old neighbour
                if y >= 0:
                    opp[y] = 3 * g1 + 2
                opp[3 * g1] = 3 * g  # b->m pairs with m->b
                opp[3 * g] = 3 * g1
            else:
                opp[3 * g] = -1
            did = True
            break
        if not did:
            f += 1
    return nv, nf, False


@_jit
def _live_out(F, v, h1, h2, h3, h4, buf, na, buf2, nb):
    """A live half-edge leaving v after a collapse: h1 or h3 themselves, or the successors of
    h2 or h4 (which end at v), or any live one of the two old rings; -1 if none."""
    for h, succ in ((h1, False), (h2, True), (h3, False), (h4, True)):
        if h >= 0:
            g = _nxt(h) if succ else h
            if F[g // 3, 0] >= 0 and _org(F, g) == v:
                return g
    for i in range(na):
        if F[buf[i] // 3, 0] >= 0 and _org(F, buf[i]) == v:
            return buf[i]
    for i in range(nb):
        if F[buf2[i] // 3, 0] >= 0 and _org(F, buf2[i]) == v:
            return buf2[i]
    return -1


@_jit_inline
def _stitch(opp, h):
    """Before h's face goes: its other two edges' outer half-edges become each other's opposites
    (or a border, where one has none). Returns them: (across next(h), across prev(h))."""
    x1, x2 = opp[_nxt(h)], opp[_prv(h)]
    if x1 >= 0:
        opp[x1] = x2
    if x2 >= 0:
        opp[x2] = x1
    return x1, x2


@_jit
def _collapse_short(V, F, opp, vh, bnd, nf, lo2, hi2, buf, buf2, nrm, nrm2):
    """Collapse edges shorter than sqrt(lo2) (module docstring); returns the number collapsed.

    Each short edge a → b goes into b (a border vertex is the one kept: :func:`_edge_to_collapse`),
    placed at b or at the edge's midpoint, when the link condition holds (:func:`_link_ok`), its
    two opposite vertices keep their valence (:func:`_keeps_valence`) and no edge grows beyond
    sqrt(hi2) nor any face turns (:func:`_moves_ok`)."""
    count = 0
    mark = np.zeros(V.shape[0], np.int64)
    stamp = 0
    for f in range(nf):
        for k in range(3):
            if F[f, 0] < 0:
                break
            if _len2(V, F[f, k], F[f, (k + 1) % 3]) >= lo2:
                continue
            h, o, a, b, ok = _edge_to_collapse(F, opp, bnd, 3 * f + k)
            if not ok:
                continue
            border_edge = o < 0
            px, py, pz = V[b, 0], V[b, 1], V[b, 2]
            if bnd[a] == bnd[b]:
                px, py, pz = 0.5 * (V[a, 0] + V[b, 0]), 0.5 * (V[a, 1] + V[b, 1]), 0.5 * (V[a, 2] + V[b, 2])
            c = _dst(F, _nxt(h))
            d = -1 if o < 0 else _dst(F, _nxt(o))
            if border_edge and opp[_nxt(h)] < 0 and opp[_prv(h)] < 0:
                continue  # a triangle on its own: collapsing it would leave a dangling edge
            na = _ring(F, opp, vh, a, buf)[0]
            nb = _ring(F, opp, vh, b, buf2)[0]
            stamp += 1
            if not _link_ok(F, buf, na, buf2, nb, mark, stamp, a, c, d, border_edge):
                continue
            if not _keeps_valence(F, opp, vh, c, buf2) or (d >= 0 and not _keeps_valence(F, opp, vh, d, buf2)):
                continue
            nb = _ring(F, opp, vh, b, buf2)[0]  # buf2 was the scratch of the valence checks
            if not _moves_ok(V, F, h, o, a, b, px, py, pz, buf, na, buf2, nb, hi2, nrm, nrm2):
                continue
            _collapse(V, F, opp, vh, bnd, h, o, a, b, c, d, px, py, pz, buf, na, buf2, nb)
            count += 1
            break
    return count


@_jit
def _edge_to_collapse(F, opp, bnd, h):
    """``(h, o, a, b, ok)``: half-edge h (and its opposite o) oriented a → b so that a border
    vertex is the one kept (b); ok is False when the edge must stay: an interior edge between two
    border vertices, or a border edge with only a on the border."""
    f, k = h // 3, h % 3
    a, b = F[f, k], F[f, (k + 1) % 3]
    o = opp[h]
    if o >= 0 and bnd[a] and bnd[b]:
        return h, o, a, b, False
    if bnd[a] and not bnd[b]:
        if o < 0:
            return h, o, a, b, False
        return o, h, b, a, True
    return h, o, a, b, True


@_jit
def _link_ok(F, buf, na, buf2, nb, mark, stamp, a, c, d, border_edge):
    """The link condition: the common neighbours of a (ring ``buf[:na]``) and b (ring
    ``buf2[:nb]``) are exactly c (and d across an interior edge). ``mark`` holds ``stamp`` for
    a's neighbours (a fresh stamp per call)."""
    for i in range(na):
        mark[_dst(F, buf[i])] = stamp
        mark[_org(F, _prv(buf[i]))] = stamp
    common = 0
    for i in range(nb):
        for w in (_dst(F, buf2[i]), _org(F, _prv(buf2[i]))):
            if w != a and mark[w] == stamp:
                mark[w] = -stamp  # count once
                common += 1
                if w != c and w != d:
                    return False
    return common == (1 if border_edge else 2)


@_jit
def _keeps_valence(F, opp, vh, v, buf):
    """v keeps at least 3 neighbours (2 on a border) after losing one to the collapse."""
    n, border = _ring(F, opp, vh, v, buf)
    return n + (1 if border else 0) - 1 >= (2 if border else 3)


@_jit
def _moves_ok(V, F, h, o, a, b, px, py, pz, buf, na, buf2, nb, hi2, nrm, nrm2):
    """Moving a and b to p makes no edge of their rings longer than sqrt(hi2) and turns no face
    over, by more than 60 degrees, or into a degenerate one (the two collapsed faces aside)."""
    for r in range(2):
        n_r = na if r == 0 else nb
        ring = buf if r == 0 else buf2
        moved = a if r == 0 else b
        for i in range(n_r):
            g = ring[i] // 3
            if g == h // 3 or (o >= 0 and g == o // 3):
                continue
            w = _dst(F, ring[i])
            dx, dy, dz = V[w, 0] - px, V[w, 1] - py, V[w, 2] - pz
            if dx * dx + dy * dy + dz * dz > hi2:
                return False
            _face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm)
            sx, sy, sz = V[moved, 0], V[moved, 1], V[moved, 2]
            V[moved, 0], V[moved, 1], V[moved, 2] = px, py, pz
            _face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm2)
            V[moved, 0], V[moved, 1], V[moved, 2] = sx, sy, sz
            dot = nrm[0] * nrm2[0] + nrm[1] * nrm2[1] + nrm[2] * nrm2[2]
            n1 = nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]
            n2 = nrm2[0] * nrm2[0] + nrm2[1] * nrm2[1] + nrm2[2] * nrm2[2]
            # turning over, or by more than 60 degrees, or becoming degenerate
            if dot <= 0.0 or dot * dot < 0.25 * n1 * n2 or n2 <= 1e-24 * n1:
                return False
    return True


@_jit
def _collapse(V, F, opp, vh, bnd, h, o, a, b, c, d, px, py, pz, buf, na, buf2, nb):
    """Collapse a into b at p: every corner of a becomes b, the two faces of the edge go (their
    outer half-edges stitched), and the half-edge and border tables of b, c and d are renewed."""
    for i in range(na):
        g = buf[i] // 3
        F[g, buf[i] % 3] = b
    f0 = h // 3
    x1, x2 = _stitch(opp, h)
    y1, y2 = _stitch(opp, o) if o >= 0 else (-1, -1)
    for g in (f0, -1 if o < 0 else o // 3):
        if g < 0:
            continue
        for q in range(3):
            opp[3 * g + q] = -1
            F[g, q] = -1
    # a live half-edge leaving a neighbour, if it still has one (c and d may be left
    # without a face: a triangle hanging on the collapsed edge)
    vh[a] = -1
    vh[b] = _live_out(F, b, x2, x1, y2 if o >= 0 else -1, y1 if o >= 0 else -1, buf, na, buf2, nb)
    vh[c] = _live_out(F, c, x1, x2, -1, -1, buf, 0, buf2, 0)
    if o >= 0:
        vh[d] = _live_out(F, d, y1, y2, -1, -1, buf, 0, buf2, 0)
    V[b, 0], V[b, 1], V[b, 2] = px, py, pz
    for w in (b, c, d):
        if w >= 0:
            bnd[w] = _ring(F, opp, vh, w, buf)[1] if vh[w] >= 0 else False


@_jit_inline
def _shape(V, a, b, c):
    """4√3·area / (sum of squared edge lengths): 1 for an equilateral triangle, 0 for a degenerate one."""
    u0, u1, u2 = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
    w0, w1, w2 = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
    x, y, z = u1 * w2 - u2 * w1, u2 * w0 - u0 * w2, u0 * w1 - u1 * w0
    e = (u0 * u0 + u1 * u1 + u2 * u2) + (w0 * w0 + w1 * w1 + w2 * w2) + _len2(V, b, c)
    return 2.0 * np.sqrt(3.0) * np.sqrt(x * x + y * y + z * z) / e if e > 0.0 else 0.0


@_jit
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


@_jit
def _flip_edges(V, F, opp, vh, bnd, nf, nv, buf, nrm, nrm2):
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
            c = _dst(F, _nxt(h))
            d = _dst(F, _nxt(o))
            if c == d:
                continue
            va, vb, vc, vd = val[a], val[b], val[c], val[d]
            ta, tb, tc, td = 4 if bnd[a] else 6, 4 if bnd[b] else 6, 4 if bnd[c] else 6, 4 if bnd[d] else 6
            if va <= (2 if bnd[a] else 3) or vb <= (2 if bnd[b] else 3):
                continue
            before = (va - ta) ** 2 + (vb - tb) ** 2 + (vc - tc) ** 2 + (vd - td) ** 2
            after = (va - 1 - ta) ** 2 + (vb - 1 - tb) ** 2 + (vc + 1 - tc) ** 2 + (vd + 1 - td) ** 2
            if after >= before:
                continue
            # the two new faces (c, a, d) and (d, b, c) must face the way the old ones did
            _face_normal(V, a, b, c, nrm)
            _face_normal(V, b, a, d, nrm2)
            sx, sy, sz = nrm[0] + nrm2[0], nrm[1] + nrm2[1], nrm[2] + nrm2[2]
            _face_normal(V, c, a, d, nrm)
            _face_normal(V, d, b, c, nrm2)
            n1 = nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]
            n2 = nrm2[0] * nrm2[0] + nrm2[1] * nrm2[1] + nrm2[2] * nrm2[2]
            s2 = sx * sx + sy * sy + sz * sz
            d1 = nrm[0] * sx + nrm[1] * sy + nrm[2] * sz
            d2 = nrm2[0] * sx + nrm2[1] * sy + nrm2[2] * sz
            if d1 <= 0.0 or d2 <= 0.0 or d1 * d1 < 0.25 * n1 * s2 or d2 * d2 < 0.25 * n2 * s2:
                continue
            # nor may the worse of the two faces lose more than half its shape quality (a
            # valence-driven flip across a flat, skinny quad would make a needle)
            q_old = min(_shape(V, a, b, c), _shape(V, b, a, d))
            if min(_shape(V, c, a, d), _shape(V, d, b, c)) < 0.5 * q_old:
                continue
            if _connected(F, opp, vh, c, d, buf):
                continue
            g = o // 3
            x_bc, x_ca = opp[_nxt(h)], opp[_prv(h)]
            x_ad, x_db = opp[_nxt(o)], opp[_prv(o)]
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
            count += 1
            break  # face f changed: its other edges are visited in the next round
    return count


@_jit
def _relax(V, F, opp, vh, bnd, nv, buf, nrm):
    """Tangential relaxation of the interior vertices (Jacobi: all from the old positions)."""
    P = V[:nv].copy()
    for v in range(nv):
        if vh[v] < 0 or bnd[v]:
            continue
        n, b = _ring(F, opp, vh, v, buf)
        if b or n < 3:
            continue
        qx = qy = qz = 0.0
        sx = sy = sz = 0.0
        for i in range(n):
            w = _dst(F, buf[i])
            qx += V[w, 0]
            qy += V[w, 1]
            qz += V[w, 2]
            g = buf[i] // 3
            _face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm)
            sx += nrm[0]
            sy += nrm[1]
            sz += nrm[2]
        qx, qy, qz = qx / n, qy / n, qz / n
        s2 = sx * sx + sy * sy + sz * sz
        dx, dy, dz = qx - V[v, 0], qy - V[v, 1], qz - V[v, 2]
        if s2 > 0.0:
            t = (dx * sx + dy * sy + dz * sz) / s2
            dx, dy, dz = dx - t * sx, dy - t * sy, dz - t * sz
        P[v, 0], P[v, 1], P[v, 2] = V[v, 0] + dx, V[v, 1] + dy, V[v, 2] + dz
    V[:nv] = P


@_jit
def _remesh(V0, F0, target, iterations, v_cap, f_cap, rounds):
    """Botsch-Kobbelt remeshing of a clean mesh; returns (V, F, nv, nf, overflow)."""
    nv, nf = V0.shape[0], F0.shape[0]
    V = np.zeros((v_cap, 3))
    V[:nv] = V0
    F = np.full((f_cap, 3), -1, np.int64)
    F[:nf] = F0
    opp = np.full(3 * f_cap, -1, np.int64)
    opp[: 3 * nf] = _pair_halfedges(F0, nf)
    vh = np.full(v_cap, -1, np.int64)
    vh[:nv] = _vertex_halfedges(F0, nf, nv)
    bnd = np.zeros(v_cap, np.bool_)
    bnd[:nv] = _border_flags(F0, opp, vh, nv)
    hi2 = (4.0 / 3.0 * target) ** 2
    lo2 = (4.0 / 5.0 * target) ** 2
    buf = np.empty(2 * _MAX_VALENCE + 2, np.int64)
    buf2 = np.empty(2 * _MAX_VALENCE + 2, np.int64)
    nrm = np.empty(3)
    nrm2 = np.empty(3)
    for _ in range(iterations):
        nv, nf, overflow = _split_long(V, F, opp, vh, bnd, nv, nf, hi2)
        if overflow:
            return V, F, nv, nf, True
        for _r in range(rounds):  # a collapse can make a neighbouring edge collapsible only later
            if _collapse_short(V, F, opp, vh, bnd, nf, lo2, hi2, buf, buf2, nrm, nrm2) == 0:
                break
        for _r in range(rounds):
            if _flip_edges(V, F, opp, vh, bnd, nf, nv, buf, nrm, nrm2) == 0:
                break
        _relax(V, F, opp, vh, bnd, nv, buf, nrm)
    return V, F, nv, nf, False


@_jit
def _ranks(used):
    """Each marked index's rank among the marked ones (-1 for the others), and their count."""
    rank = np.full(used.shape[0], -1, np.int64)
    n = 0
    for i in range(used.shape[0]):
        if used[i]:
            rank[i] = n
            n += 1
    return rank, n


@_jit
def _live(F, nv):
    """The live faces of F (first index >= 0) renumbered into the vertices they use, and those
    vertices' old indices (ascending)."""
    used = np.zeros(nv, np.bool_)
    n_f = 0
    for f in range(F.shape[0]):
        if F[f, 0] >= 0:
            n_f += 1
            for k in range(3):
                used[F[f, k]] = True
    new_id, n = _ranks(used)
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


def _compact(V: np.ndarray, F: np.ndarray, nv: int, nf: int) -> tuple[np.ndarray, np.ndarray]:
    keep, f = _live(F[:nf], nv)
    return V[keep], f


def remesh_clean(
    vertices: np.ndarray, faces: np.ndarray, target: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing (module docstring) of a mesh that :func:`clean_mesh` returned, towards
    edge length ``target`` (same unit as the vertices)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if iterations <= 0 or len(f) == 0:
        return v, f
    p = v[f]
    area = 0.5 * float(np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())
    if not (np.isfinite(area) and target > 0 and np.isfinite(target)):
        raise NirspiError(f"remeshing: needs finite vertices and an edge length > 0, got length {target!r}")
    # an equilateral triangle of edge 4/5 target is the smallest a finished mesh has on average;
    # splitting before collapsing can transiently need more: grow and retry on overflow
    estimate = int(area / (np.sqrt(3.0) / 4.0 * (0.8 * target) ** 2))
    if estimate > MAX_FACES:
        raise NirspiError(
            f"remeshing: about {estimate} faces at edge length {target:.3g} for a surface of area {area:.3g}; "
            f"more than {MAX_FACES} (raise remesh_edge_factor)"
        )
    room = 2 * MAX_FACES + 1024
    f_cap = min(2 * (len(f) + estimate) + 1024, room)
    while True:
        V, F, nv, nf, overflow = _remesh(v, f, float(target), int(iterations), len(v) + f_cap, f_cap, _PASSES)
        if not overflow:
            return _compact(V, F, nv, nf)
        if f_cap >= room:
            break
        f_cap = min(4 * f_cap, room)
    raise NirspiError(
        f"remeshing: the mesh grew past {room} faces of room at edge length {target:.3g} (raise remesh_edge_factor)"
    )


def clean_and_remesh_compiled(
    vertices_m: np.ndarray,
    faces: np.ndarray,
    spacing_m: float,
    iterations: int = 3,
    edge_factor: float = 1.0,
    max_hole_edges: int = 30,
    min_component_faces: int = 10,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """The contract of :func:`nirspi_pipe.mesh.remesh.clean_and_remesh`, compiled (module
    docstring): metres in, metres out; an empty or tiny mesh is returned unchanged."""
    v = np.asarray(vertices_m, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    info: dict[str, float] = {"faces_before_remesh": int(len(f))}
    if len(f) < 4 or not spacing_m > 0:
        return v, f, info
    v, f, cinfo = clean_mesh(v, f, int(max_hole_edges), int(min_component_faces))
    info.update(cinfo)
    if iterations > 0 and len(f):
        v, f = remesh_clean(v, f, float(spacing_m * edge_factor), int(iterations))
    info["faces_after_remesh"] = int(len(f))
    return v, f, info


def warm_up() -> bool:
    """Compile (or load from numba's on-disk cache) every kernel of this module by cleaning and
    remeshing a small grid with a hole; True when numba is there and it worked. Called when a
    surface stage is built, so that compilation is never part of a stage's time."""
    if njit is None:
        return False
    n = 6
    x, y = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64))
    v = np.column_stack([x.ravel(), y.ravel(), 0.1 * x.ravel() * y.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    f = f[np.all(f != idx[2, 2], axis=1)]  # a hole around one vertex
    try:  # a cache that does not load is rebuilt once, with a warning naming it (jitcache)
        out_v, out_f, _ = jitcache.rebuild_on_failure(
            lambda: clean_and_remesh_compiled(v, f, 1.0, 1, 0.8, 30, 1), what="the remesher", kernels=("isotropic",)
        )
    except Exception:  # noqa: BLE001 - any failure means "not available": the caller falls back
        return False
    return len(out_f) > 0
