"""The power crust's faces from the labelled regular triangulation, compiled with numba.

Step 3 of :func:`nirspi_pipe.mesh.powercrust.power_crust` after Qhull: every edge ``(a, b)`` of
the regular triangulation whose poles are labelled differently (one inner, one outer) is dual to
a power-crust face, the polygon of the power centres of the tetrahedra around the edge.

1. The mixed edges of every tetrahedron are gathered and grouped by edge (a stable sort, so each
   ring keeps the tetrahedra's order). An edge whose ring is not closed (some ring vertex not seen
   exactly twice, e.g. on the hull) gives no face.
2. Each ring is ordered by angle around the edge, about the ring's own centroid (the line through
   the two poles need not pierce the polygon).
3. Power centres closer than ``wtol`` are welded (union of all pairs within ``wtol``, found by a
   sweep along x; each welded vertex is the mean of its members): co-spherical poles give several
   tetrahedra with one power centre, and near-coincident ones make sliver triangles.
4. Repeated vertices along a ring are dropped; a polygon with three or more vertices is
   triangulated around its centroid (a hexagon gives six equilateral triangles where a fan from
   one vertex would give slivers) and oriented from the inner pole to the outer one.

This replaced about thirty numpy passes over the rings' arrays with one compiled pass and gives
the same triangles (checked on the 16 Table 6 clouds when it was written; ``nirspi-bench mesh3d``
times the surface stage it is part of). Fixed order, float64, no fast-math: the same input gives
the same bits on every CPU (tests/test_mesh_remesh_compiled.py finds no fused multiply-add).
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.mesh.halfedges import find_root, jit_kernel, live_faces, ranks

__all__ = ["crust_faces", "power_centres"]

# the six edges of a tetrahedron, each with the two other vertices (the ring pair)
_EDGES = np.array([(0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)], dtype=np.int64)


@jit_kernel
def _centres(T, W, use_w):
    t = T.shape[0]
    c = np.zeros((t, 3))
    ok = np.zeros(t, np.bool_)
    for i in range(t):
        x0, y0, z0 = T[i, 0, 0], T[i, 0, 1], T[i, 0, 2]
        l0 = x0 * x0 + y0 * y0 + z0 * z0
        if use_w:
            l0 = l0 - W[i, 0]
        x1, y1, z1 = T[i, 1, 0], T[i, 1, 1], T[i, 1, 2]
        x2, y2, z2 = T[i, 2, 0], T[i, 2, 1], T[i, 2, 2]
        x3, y3, z3 = T[i, 3, 0], T[i, 3, 1], T[i, 3, 2]
        # rows r_j = 2 (p_j - p_0), right-hand sides b_j = lift_j - lift_0
        a0, a1, a2 = 2.0 * (x1 - x0), 2.0 * (y1 - y0), 2.0 * (z1 - z0)
        b0, b1, b2 = 2.0 * (x2 - x0), 2.0 * (y2 - y0), 2.0 * (z2 - z0)
        d0, d1, d2 = 2.0 * (x3 - x0), 2.0 * (y3 - y0), 2.0 * (z3 - z0)
        l1, l2, l3 = x1 * x1 + y1 * y1 + z1 * z1, x2 * x2 + y2 * y2 + z2 * z2, x3 * x3 + y3 * y3 + z3 * z3
        if use_w:
            l1, l2, l3 = l1 - W[i, 1], l2 - W[i, 2], l3 - W[i, 3]
        q0, q1, q2 = l1 - l0, l2 - l0, l3 - l0
        scale = max(abs(a0), abs(b0), abs(d0), abs(a1), abs(b1), abs(d1), abs(a2), abs(b2), abs(d2))
        c23x, c23y, c23z = b1 * d2 - b2 * d1, b2 * d0 - b0 * d2, b0 * d1 - b1 * d0
        c31x, c31y, c31z = d1 * a2 - d2 * a1, d2 * a0 - d0 * a2, d0 * a1 - d1 * a0
        c12x, c12y, c12z = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        det = a0 * c23x + a1 * c23y + a2 * c23z
        if abs(det) > 1e-12 * max(scale**3.0, 1e-300):
            ok[i] = True
            c[i, 0] = (q0 * c23x + q1 * c31x + q2 * c12x) / det
            c[i, 1] = (q0 * c23y + q1 * c31y + q2 * c12y) / det
            c[i, 2] = (q0 * c23z + q1 * c31z + q2 * c12z) / det
    return c, ok


def power_centres(tets: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Compiled body of :func:`nirspi_pipe.mesh.powercrust.circumcentres` (same IEEE operations
    in the same order): centres ``(t, 3)`` and the non-degenerate flag ``(t,)``."""
    T = np.ascontiguousarray(tets, dtype=np.float64)
    W = np.zeros((len(T), 4)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    return _centres(T, W, weights is not None)


@jit_kernel
def _stable_order(key, m):
    """``np.argsort(key, kind="stable")`` for keys ``a*m + b`` (0 <= b < m): a counting sort by
    ``a``, then an insertion sort by ``b`` inside each (small) bucket."""
    k = key.shape[0]
    na = 0
    for i in range(k):
        na = max(na, key[i] // m + 1)
    start = np.zeros(na + 1, np.int64)
    for i in range(k):
        start[key[i] // m + 1] += 1
    for a in range(na):
        start[a + 1] += start[a]
    fill = start[:na].copy()
    order = np.empty(k, np.int64)
    for i in range(k):
        a = key[i] // m
        order[fill[a]] = i
        fill[a] += 1
    for a in range(na):
        for q in range(start[a] + 1, start[a + 1]):
            v = order[q]
            r = q - 1
            while r >= start[a] and key[order[r]] > key[v]:
                order[r + 1] = order[r]
                r -= 1
            order[r + 1] = v
    return order


@jit_kernel
def _weld(P, wtol):
    """Cluster of each point of P (n, 3): connected components of the pairs within wtol,
    numbered in order of their smallest member; and the clusters' mean positions."""
    n = P.shape[0]
    parent = np.arange(n)
    order = np.argsort(P[:, 0], kind="mergesort")
    w2 = wtol * wtol
    for i in range(n):
        p = order[i]
        for j in range(i + 1, n):
            q = order[j]
            dx = P[q, 0] - P[p, 0]
            if dx > wtol:
                break
            dy, dz = P[q, 1] - P[p, 1], P[q, 2] - P[p, 2]
            if dx * dx + dy * dy + dz * dz <= w2:
                a, b = find_root(parent, p), find_root(parent, q)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    label = np.full(n, -1, np.int64)
    cl = np.empty(n, np.int64)
    n_cl = 0
    for i in range(n):
        r = find_root(parent, i)
        if label[r] < 0:
            label[r] = n_cl
            n_cl += 1
        cl[i] = label[r]
    pos = np.zeros((n_cl, 3))
    cnt = np.zeros(n_cl)
    for i in range(n):
        c = cl[i]
        pos[c, 0] += P[i, 0]
        pos[c, 1] += P[i, 1]
        pos[c, 2] += P[i, 2]
        cnt[c] += 1.0
    for c in range(n_cl):
        pos[c, 0] /= cnt[c]
        pos[c, 1] /= cnt[c]
        pos[c, 2] /= cnt[c]
    return cl, pos


@jit_kernel
def _crust(poles, tets, centres, inner, wtol, edges):
    """The four steps of the module docstring: ``(vertices, faces, polygons)``."""
    m = poles.shape[0]
    key, tid, oth = _mixed_edges(tets, inner, edges, m)
    order = _stable_order(key, m)
    ring_t, ring_start, ring_ab, n_ring = _closed_rings(poles, centres, key, tid, oth, order, m)
    id_of, cl, vpos = _weld_ring_centres(centres, ring_t, wtol)
    return _fan_polygons(poles, inner, ring_t, ring_start, ring_ab, n_ring, id_of, cl, vpos)


@jit_kernel
def _mixed_edges(tets, inner, edges, m):
    """Step 1: every edge of every tetrahedron between an inner and an outer pole: its key
    ``a·m + b`` (a < b), its tetrahedron, and the two other vertices (the ring pair)."""
    t = tets.shape[0]
    k = 0
    for i in range(t):
        for e in range(6):
            if inner[tets[i, edges[e, 0]]] != inner[tets[i, edges[e, 1]]]:
                k += 1
    key = np.empty(k, np.int64)
    tid = np.empty(k, np.int64)
    oth = np.empty((k, 2), np.int64)
    k = 0
    for i in range(t):
        for e in range(6):
            a, b = tets[i, edges[e, 0]], tets[i, edges[e, 1]]
            if inner[a] != inner[b]:
                key[k] = min(a, b) * m + max(a, b)
                tid[k] = i
                oth[k, 0], oth[k, 1] = tets[i, edges[e, 2]], tets[i, edges[e, 3]]
                k += 1
    return key, tid, oth


@jit_kernel
def _is_closed(oth, order, i, j):
    """The ring of entries ``order[i:j]`` is closed: each of its vertices is seen exactly twice."""
    for q in range(i, j):
        for side in range(2):
            v = oth[order[q], side]
            seen = 0
            for r in range(i, j):
                seen += (oth[order[r], 0] == v) + (oth[order[r], 1] == v)
            if seen != 2:
                return False
    return True


@jit_kernel
def _closed_rings(poles, centres, key, tid, oth, order, m):
    """Step 2: the closed rings, each one's tetrahedra ordered by angle around its edge.
    Returns ``(tetrahedra ring after ring, ring starts, ring edges (a, b), number of rings)``."""
    k = key.shape[0]
    ring_t = np.empty(k, np.int64)
    ring_start = np.empty(k + 1, np.int64)
    ring_ab = np.empty((k, 2), np.int64)
    n_ring = 0
    n_t = 0
    ang = np.empty(64)
    idx = np.empty(64, np.int64)
    i = 0
    while i < k:
        j = i
        while j < k and key[order[j]] == key[order[i]]:
            j += 1
        if _is_closed(oth, order, i, j):
            a, b = key[order[i]] // m, key[order[i]] % m
            if j - i > ang.shape[0]:
                ang = np.empty(2 * (j - i))
                idx = np.empty(2 * (j - i), np.int64)
            _order_by_angle(poles, centres, tid, order, i, j, a, b, ang, idx)
            ring_start[n_ring] = n_t
            ring_ab[n_ring, 0], ring_ab[n_ring, 1] = a, b
            for q in range(j - i):
                ring_t[n_t] = idx[q]
                n_t += 1
            n_ring += 1
        i = j
    ring_start[n_ring] = n_t
    return ring_t[:n_t], ring_start, ring_ab, n_ring


@jit_kernel
def _order_by_angle(poles, centres, tid, order, i, j, a, b, ang, idx):
    """The tetrahedra ``tid[order[i:j]]`` into ``idx[:j - i]``, by the angle of their power
    centres around the axis a → b about the ring's centroid (a stable insertion sort)."""
    s = j - i
    ax, ay, az = poles[b, 0] - poles[a, 0], poles[b, 1] - poles[a, 1], poles[b, 2] - poles[a, 2]
    nrm = np.sqrt(ax * ax + ay * ay + az * az)
    ax, ay, az = ax / nrm, ay / nrm, az / nrm
    if abs(ax) < 0.9:
        ux, uy, uz = 0.0, az, -ay  # axis x (1, 0, 0)
    else:
        ux, uy, uz = -az, 0.0, ax  # axis x (0, 1, 0)
    nu = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / nu, uy / nu, uz / nu
    wx, wy, wz = ay * uz - az * uy, az * ux - ax * uz, ax * uy - ay * ux
    cx = cy = cz = 0.0
    for q in range(i, j):
        c = tid[order[q]]
        cx += centres[c, 0]
        cy += centres[c, 1]
        cz += centres[c, 2]
    cx, cy, cz = cx / s, cy / s, cz / s
    for q in range(s):
        c = tid[order[i + q]]
        rx, ry, rz = centres[c, 0] - cx, centres[c, 1] - cy, centres[c, 2] - cz
        ang[q] = np.arctan2(rx * wx + ry * wy + rz * wz, rx * ux + ry * uy + rz * uz)
        idx[q] = c
    for q in range(1, s):  # stable insertion sort by angle
        av, iv = ang[q], idx[q]
        r = q - 1
        while r >= 0 and ang[r] > av:
            ang[r + 1] = ang[r]
            idx[r + 1] = idx[r]
            r -= 1
        ang[r + 1] = av
        idx[r + 1] = iv


@jit_kernel
def _weld_ring_centres(centres, ring_t, wtol):
    """Step 3: the power centres the rings use, welded within ``wtol``. Returns each
    tetrahedron's index among the used ones, each used one's cluster, and the clusters' positions."""
    t = centres.shape[0]
    used = np.zeros(t, np.bool_)
    for q in range(ring_t.shape[0]):
        used[ring_t[q]] = True
    id_of, n_id = ranks(used)
    P = np.empty((n_id, 3))
    for q in range(t):
        if used[q]:
            P[id_of[q]] = centres[q]
    cl, vpos = _weld(P, wtol)
    return id_of, cl, vpos


@jit_kernel
def _fan_polygons(poles, inner, ring_t, ring_start, ring_ab, n_ring, id_of, cl, vpos):
    """Step 4: each ring's polygon of welded centres without cyclic repeats; one with three or
    more vertices is fanned around its centroid, oriented from the inner pole to the outer one."""
    n_t = ring_t.shape[0]
    n_cl = vpos.shape[0]
    vid = np.empty(max(n_t, 1), np.int64)
    faces = np.empty((max(n_t, 1), 3), np.int64)
    cen = np.empty((max(n_ring, 1), 3))
    n_f = 0
    n_poly = 0
    for r in range(n_ring):
        s0, s1 = ring_start[r], ring_start[r + 1]
        n = 0
        for q in range(s0, s1):
            v = cl[id_of[ring_t[q]]]
            prev = cl[id_of[ring_t[s1 - 1 if q == s0 else q - 1]]]
            if v != prev or s1 - s0 == 1:
                vid[n] = v
                n += 1
        if n < 3:
            continue
        cx = cy = cz = 0.0
        for q in range(n):
            cx += vpos[vid[q], 0]
            cy += vpos[vid[q], 1]
            cz += vpos[vid[q], 2]
        cen[n_poly, 0], cen[n_poly, 1], cen[n_poly, 2] = cx / n, cy / n, cz / n
        a, b = ring_ab[r, 0], ring_ab[r, 1]
        dx, dy, dz = poles[b, 0] - poles[a, 0], poles[b, 1] - poles[a, 1], poles[b, 2] - poles[a, 2]
        for q in range(n):
            v1, v2 = vid[q], vid[(q + 1) % n]
            ex, ey, ez = vpos[v1, 0] - cen[n_poly, 0], vpos[v1, 1] - cen[n_poly, 1], vpos[v1, 2] - cen[n_poly, 2]
            fx, fy, fz = vpos[v2, 0] - cen[n_poly, 0], vpos[v2, 1] - cen[n_poly, 1], vpos[v2, 2] - cen[n_poly, 2]
            along = (ey * fz - ez * fy) * dx + (ez * fx - ex * fz) * dy + (ex * fy - ey * fx) * dz
            # oriented outwards: the normal points from the inner pole's side to the outer one's
            flip = along < 0 if inner[a] else along > 0
            faces[n_f, 0] = n_cl + n_poly
            faces[n_f, 1] = v2 if flip else v1
            faces[n_f, 2] = v1 if flip else v2
            n_f += 1
        n_poly += 1
    verts = np.empty((n_cl + n_poly, 3))
    verts[:n_cl] = vpos
    verts[n_cl:] = cen[:n_poly]
    keep, new_faces = live_faces(faces[:n_f], n_cl + n_poly)
    return verts[keep], new_faces, n_poly


def crust_faces(
    poles: np.ndarray, tets: np.ndarray, centres: np.ndarray, inner: np.ndarray, wtol: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """Power-crust triangles (module docstring): ``(vertices (v, 3), faces (f, 3), polygons)``,
    the vertices in the unit of ``poles``/``centres``; ``wtol``: the welding distance, same unit."""
    return _crust(
        np.ascontiguousarray(poles, dtype=np.float64),
        np.ascontiguousarray(tets, dtype=np.int64),
        np.ascontiguousarray(centres, dtype=np.float64),
        np.ascontiguousarray(inner, dtype=np.bool_),
        float(wtol),
        _EDGES,
    )
