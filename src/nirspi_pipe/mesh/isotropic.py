"""Mesh clean-up and isotropic remeshing, compiled with numba (``remesher: compiled``).

The same two steps as :func:`nirspi_pipe.mesh.remesh.clean_and_remesh` (pymeshlab), for the small
meshes of the 3D path (a few thousand faces). On the power crusts of the 16 jobs of ``nirspi-run -m
+experiment=table6 illumination.klux=5 seed=0``, welded as the stage welds them, pymeshlab's clean-up
and remeshing took 31.9 ms per mesh and the compiled ones below 1.7 + 4.4 ms (medians,
``experiments/mesh/remesher_timing.py``); ``nirspi-bench mesh3d`` prints both, measured in the
same run.

1. **Clean-up**: :func:`nirspi_pipe.mesh.meshclean.clean_mesh` (its module docstring): equal
   vertices merged, degenerate and duplicate faces dropped, faces oriented consistently, the mesh
   cut into an edge- and vertex-manifold one, small pieces dropped and small holes closed.

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
of a stage's time. The kernels of both steps share the corner table of
:mod:`nirspi_pipe.mesh.halfedges`.
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh import jitcache
from nirspi_pipe.mesh.edgeflip import face_normal, flip_edges, len2
from nirspi_pipe.mesh.halfedges import (
    HAVE_NUMBA,
    MAX_FACES,
    MAX_VALENCE,
    border_flags,
    he_next,
    he_origin,
    he_prev,
    he_target,
    jit_inline,
    jit_kernel,
    live_faces,
    pair_halfedges,
    vertex_halfedges,
    vertex_ring,
)
from nirspi_pipe.mesh.meshclean import clean_mesh

__all__ = ["clean_and_remesh_compiled", "remesh_clean", "warm_up"]

_PASSES = 1  # collapse and flip passes per iteration (Botsch & Kobbelt: one)


# ---------------------------------------------------------------------------------------------
# remeshing
# ---------------------------------------------------------------------------------------------


@jit_kernel
def _split_long(V, F, opp, vh, bnd, nv, nf, hi2):
    """Split every edge longer than sqrt(hi2) at its midpoint (new faces are visited too; passes
    repeat until none is left). Returns (nv, nf, overflow)."""
    for _pass in range(16):
        nf0 = nf
        nv, nf, overflow = _split_pass(V, F, opp, vh, bnd, nv, nf, hi2)
        if overflow or nf == nf0:
            return nv, nf, overflow
    return nv, nf, False


@jit_kernel
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
            if len2(V, a, b) <= hi2:
                continue
            # only when the split shortens: the new edges to the opposite vertices must be shorter
            # than this one (not so in a degenerate, needle-like triangle, which flips handle)
            l2 = len2(V, a, b)
            c = F[f, (k + 2) % 3]
            mx, my, mz = 0.5 * (V[a, 0] + V[b, 0]), 0.5 * (V[a, 1] + V[b, 1]), 0.5 * (V[a, 2] + V[b, 2])
            if (mx - V[c, 0]) ** 2 + (my - V[c, 1]) ** 2 + (mz - V[c, 2]) ** 2 >= l2:
                continue
            if o >= 0:
                e = he_target(F, he_next(o))
                if (mx - V[e, 0]) ** 2 + (my - V[e, 1]) ** 2 + (mz - V[e, 2]) ** 2 >= l2:
                    continue
            if nv + 1 > V.shape[0] or nf + 2 > F.shape[0]:
                return nv, nf, True
            m = nv
            nv += 1
            V[m, 0], V[m, 1], V[m, 2] = mx, my, mz
            bnd[m] = o < 0
            # face f = (a, b, c) -> (a, m, c) and new face g = (m, b, c)
            hn = he_next(h)
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
                op = he_prev(o)  # d->b, becomes d->m
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


@jit_kernel
def _live_out(F, v, h1, h2, h3, h4, buf, na, buf2, nb):
    """A live half-edge leaving v after a collapse: h1 or h3 themselves, or the successors of
    h2 or h4 (which end at v), or any live one of the two old rings; -1 if none."""
    for h, succ in ((h1, False), (h2, True), (h3, False), (h4, True)):
        if h >= 0:
            g = he_next(h) if succ else h
            if F[g // 3, 0] >= 0 and he_origin(F, g) == v:
                return g
    for i in range(na):
        if F[buf[i] // 3, 0] >= 0 and he_origin(F, buf[i]) == v:
            return buf[i]
    for i in range(nb):
        if F[buf2[i] // 3, 0] >= 0 and he_origin(F, buf2[i]) == v:
            return buf2[i]
    return -1


@jit_inline
def _stitch(opp, h):
    """Before h's face goes: its other two edges' outer half-edges become each other's opposites
    (or a border, where one has none). Returns them: (across next(h), across prev(h))."""
    x1, x2 = opp[he_next(h)], opp[he_prev(h)]
    if x1 >= 0:
        opp[x1] = x2
    if x2 >= 0:
        opp[x2] = x1
    return x1, x2


@jit_kernel
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
            if len2(V, F[f, k], F[f, (k + 1) % 3]) >= lo2:
                continue
            h, o, a, b, ok = _edge_to_collapse(F, opp, bnd, 3 * f + k)
            if not ok:
                continue
            border_edge = o < 0
            px, py, pz = V[b, 0], V[b, 1], V[b, 2]
            if bnd[a] == bnd[b]:
                px, py, pz = 0.5 * (V[a, 0] + V[b, 0]), 0.5 * (V[a, 1] + V[b, 1]), 0.5 * (V[a, 2] + V[b, 2])
            c = he_target(F, he_next(h))
            d = -1 if o < 0 else he_target(F, he_next(o))
            if border_edge and opp[he_next(h)] < 0 and opp[he_prev(h)] < 0:
                continue  # a triangle on its own: collapsing it would leave a dangling edge
            na = vertex_ring(F, opp, vh, a, buf)[0]
            nb = vertex_ring(F, opp, vh, b, buf2)[0]
            stamp += 1
            if not _link_ok(F, buf, na, buf2, nb, mark, stamp, a, c, d, border_edge):
                continue
            if not _keeps_valence(F, opp, vh, c, buf2) or (d >= 0 and not _keeps_valence(F, opp, vh, d, buf2)):
                continue
            nb = vertex_ring(F, opp, vh, b, buf2)[0]  # buf2 was the scratch of the valence checks
            if not _moves_ok(V, F, h, o, a, b, px, py, pz, buf, na, buf2, nb, hi2, nrm, nrm2):
                continue
            _collapse(V, F, opp, vh, bnd, h, o, a, b, c, d, px, py, pz, buf, na, buf2, nb)
            count += 1
            break
    return count


@jit_kernel
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


@jit_kernel
def _link_ok(F, buf, na, buf2, nb, mark, stamp, a, c, d, border_edge):
    """The link condition: the common neighbours of a (ring ``buf[:na]``) and b (ring
    ``buf2[:nb]``) are exactly c (and d across an interior edge). ``mark`` holds ``stamp`` for
    a's neighbours (a fresh stamp per call)."""
    for i in range(na):
        mark[he_target(F, buf[i])] = stamp
        mark[he_origin(F, he_prev(buf[i]))] = stamp
    common = 0
    for i in range(nb):
        for w in (he_target(F, buf2[i]), he_origin(F, he_prev(buf2[i]))):
            if w != a and mark[w] == stamp:
                mark[w] = -stamp  # count once
                common += 1
                if w != c and w != d:
                    return False
    return common == (1 if border_edge else 2)


@jit_kernel
def _keeps_valence(F, opp, vh, v, buf):
    """v keeps at least 3 neighbours (2 on a border) after losing one to the collapse."""
    n, border = vertex_ring(F, opp, vh, v, buf)
    return n + (1 if border else 0) - 1 >= (2 if border else 3)


@jit_kernel
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
            w = he_target(F, ring[i])
            dx, dy, dz = V[w, 0] - px, V[w, 1] - py, V[w, 2] - pz
            if dx * dx + dy * dy + dz * dz > hi2:
                return False
            face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm)
            sx, sy, sz = V[moved, 0], V[moved, 1], V[moved, 2]
            V[moved, 0], V[moved, 1], V[moved, 2] = px, py, pz
            face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm2)
            V[moved, 0], V[moved, 1], V[moved, 2] = sx, sy, sz
            dot = nrm[0] * nrm2[0] + nrm[1] * nrm2[1] + nrm[2] * nrm2[2]
            n1 = nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]
            n2 = nrm2[0] * nrm2[0] + nrm2[1] * nrm2[1] + nrm2[2] * nrm2[2]
            # turning over, or by more than 60 degrees, or becoming degenerate
            if dot <= 0.0 or dot * dot < 0.25 * n1 * n2 or n2 <= 1e-24 * n1:
                return False
    return True


@jit_kernel
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
            bnd[w] = vertex_ring(F, opp, vh, w, buf)[1] if vh[w] >= 0 else False


@jit_kernel
def _relax(V, F, opp, vh, bnd, nv, buf, nrm):
    """Tangential relaxation of the interior vertices (Jacobi: all from the old positions)."""
    P = V[:nv].copy()
    for v in range(nv):
        if vh[v] < 0 or bnd[v]:
            continue
        n, b = vertex_ring(F, opp, vh, v, buf)
        if b or n < 3:
            continue
        qx = qy = qz = 0.0
        sx = sy = sz = 0.0
        for i in range(n):
            w = he_target(F, buf[i])
            qx += V[w, 0]
            qy += V[w, 1]
            qz += V[w, 2]
            g = buf[i] // 3
            face_normal(V, F[g, 0], F[g, 1], F[g, 2], nrm)
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


@jit_kernel
def _remesh(V0, F0, target, iterations, v_cap, f_cap, rounds):
    """Botsch-Kobbelt remeshing of a clean mesh; returns (V, F, nv, nf, overflow)."""
    nv, nf = V0.shape[0], F0.shape[0]
    V = np.zeros((v_cap, 3))
    V[:nv] = V0
    F = np.full((f_cap, 3), -1, np.int64)
    F[:nf] = F0
    opp = np.full(3 * f_cap, -1, np.int64)
    opp[: 3 * nf] = pair_halfedges(F0, nf)
    vh = np.full(v_cap, -1, np.int64)
    vh[:nv] = vertex_halfedges(F0, nf, nv)
    bnd = np.zeros(v_cap, np.bool_)
    bnd[:nv] = border_flags(F0, opp, vh, nv)
    hi2 = (4.0 / 3.0 * target) ** 2
    lo2 = (4.0 / 5.0 * target) ** 2
    buf = np.empty(2 * MAX_VALENCE + 2, np.int64)
    buf2 = np.empty(2 * MAX_VALENCE + 2, np.int64)
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
            if flip_edges(V, F, opp, vh, bnd, nf, nv, buf, nrm, nrm2) == 0:
                break
        _relax(V, F, opp, vh, bnd, nv, buf, nrm)
    return V, F, nv, nf, False


def _compact(V: np.ndarray, F: np.ndarray, nv: int, nf: int) -> tuple[np.ndarray, np.ndarray]:
    keep, f = live_faces(F[:nf], nv)
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
    if not HAVE_NUMBA:
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
            lambda: clean_and_remesh_compiled(v, f, 1.0, 1, 0.8, 30, 1),
            what="the remesher",
            kernels=("halfedges", "meshclean", "edgeflip", "isotropic"),
        )
    except Exception:  # noqa: BLE001 - any failure means "not available": the caller falls back
        return False
    return len(out_f) > 0
