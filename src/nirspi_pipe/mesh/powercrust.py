"""Surface ``power_crust``: the power crust of Amenta, Choi & Kolluri (2001) on scipy's Qhull.

1. **Poles.** The Voronoi diagram of the samples is the dual of their Delaunay tetrahedralisation
   (``scipy.spatial.Delaunay``, Qhull): its vertices are the tetrahedra's circumcentres. Eight
   box corners far outside the samples are added so every sample's Voronoi cell is bounded. For
   each sample ``s`` the positive pole ``p+`` is its cell's vertex farthest from ``s``; the
   negative pole ``p−`` is the farthest vertex with ``(p− − s)·(p+ − s) < 0``. Each pole carries
   its polar ball, radius ``r = |p − s|`` (the circumradius: the ball is empty of samples).
2. **Power diagram by lifting.** The poles with weights ``r²`` are lifted to
   ``(p, |p|² − r²)`` in 4D; the lower convex hull (``scipy.spatial.ConvexHull``, Qhull, joggled)
   projects to the regular triangulation, the dual of the power diagram. Its tetrahedra's
   power centres (``|c − p_i|² − r_i²`` equal for the four poles) are the power-diagram
   vertices; an edge ``(a, b)`` of the triangulation is dual to the power-diagram face between
   the cells of ``a`` and ``b``, the polygon of the power centres of the tetrahedra around it.
3. **Labelling** poles inner or outer, then the **power crust** is the set of faces between an
   inner and an outer pole's cells (fan-triangulated, oriented outwards).

   * ``amenta`` (closed, well-sampled surfaces): the paper's greedy labelling. Poles on the
     convex hull of all poles start outer; a priority queue then labels the most certain pole
     first: the two poles of one sample get opposite labels with certainty ``−cos∠(p+ s p−)``;
     poles whose balls intersect deeply get the same label with certainty
     ``(r₁² + r₂² − |c₁ − c₂|²)/(2 r₁ r₂)`` (the cosine of the balls' intersection angle).
   * ``view`` (a 2.5D patch seen from the camera at the origin, the pipeline's case): a cloud
     from one depth map has no inside of its own; the one closed surface it defines is the
     boundary of the space behind the visible surface within the silhouette (the one-view
     visual hull carved by the depth). A pole is *inner* when it projects inside the sampled
     silhouette and lies farther from the camera than the nearest sample in projection, and
     *outer* otherwise (in front of the surface or outside the silhouette).

With ``closed: false`` (default) faces with a vertex farther than ``trim_factor`` × the median
sample spacing from every sample are removed: the data says nothing about the back of the
object, so the mesh is the visible sheet; ``closed: true`` keeps the whole power crust (for
``view``: the visible surface, the silhouette walls and a back cap at the bounding box).
"""

from __future__ import annotations

import heapq
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Annotated, Any

import numpy as np
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh.crustfaces import crust_faces, power_centres
from nirspi_pipe.mesh.jitcache import rebuild_on_failure
from nirspi_pipe.mesh.outputs import warm_up as warm_up_outputs
from nirspi_pipe.mesh.remesh import (
    MaxHoleEdges,
    RemeshEdgeFactor,
    Remesher,
    RemeshIterations,
    load_meshlab,
    remesh_to_cloud,
    resolve_remesher,
    sample_spacing,
)
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.types import Mesh, PointCloud

#: Grid (m) the samples are snapped to before the Delaunay/Qhull steps. Assumed: 10 nm, five orders
#: of magnitude below the cloud's sample spacing (~1 mm at 20 cm) and eight above the difference
#: measured between OpenBLAS kernel sets in the fused cloud (2e-16 m), so the combinatorial steps
#: see the same input on every CPU (issue 12) while the geometry does not move measurably.
CLOUD_QUANTUM_M = 1e-8

#: A cloud point counts as covered by the mesh when a point of the mesh (a vertex, an edge midpoint
#: or a face centroid) lies within this many sample spacings of it, plus half the face's longest
#: edge. Assumed: 2, the trim's own scale (``trim_factor`` defaults to 2 spacings), so a point the
#: trim would keep a face for counts as covered.
COVERAGE_SPACINGS = 2.0
#: Below this covered fraction the crust "lost most of the shape" (issue 44's wording): a warning.
MIN_COVERED_FRACTION = 0.5


def cloud_coverage(verts: np.ndarray, faces: np.ndarray, pts: np.ndarray, spacing: float) -> float:
    """The fraction of the cloud points ``pts`` that the mesh ``(verts, faces)`` lies near: within
    :data:`COVERAGE_SPACINGS` × ``spacing`` plus half the longest edge of the mesh's faces of a
    vertex, edge midpoint or face centroid (metres in, a fraction in [0, 1] out).

    The vertices are searched first: a point that one of them covers is covered whatever the
    other samples (the nearest of all is at most as far), so the midpoints and centroids (six in
    seven of the samples) are searched only for the points no vertex covers, usually none of a
    table3 cloud. The same distances decide: the same fraction as one search over all samples
    (tests/test_mesh_speed.py)."""
    p = np.asarray(pts, dtype=np.float64)
    if len(p) == 0:
        return 1.0
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return 0.0
    v = np.asarray(verts, dtype=np.float64)
    tri = v[f]
    edge = float(np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=-1).max())
    reach = COVERAGE_SPACINGS * spacing + 0.5 * edge
    near = cKDTree(v[np.unique(f)]).query(p, k=1)[0] <= reach
    if not near.all():
        rest = np.flatnonzero(~near)
        mids = 0.5 * (tri + np.roll(tri, -1, axis=1))
        others = np.concatenate([mids.reshape(-1, 3), tri.mean(axis=1)])
        near[rest] = cKDTree(others).query(p[rest], k=1)[0] <= reach
    return float(np.mean(near))


#: A cloud whose second singular value is below this fraction of its first lies on a line (assumed:
#: 1e-5, a 5 cm strip 0.5 µm wide, far below any surface the camera samples at ~1 mm; a line of 50
#: points with 20 nm of jitter, ratio 2e-6, gave a one-triangle mesh).
COLLINEAR_REL = 1e-5

#: Clouds farther from the camera than this many extents are centred for Qhull (assumed: 1000; the
#: project's scenes are within 10 extents; Qhull refused a 4 cm cap 1000 km away).
FAR_EXTENTS = 1000.0

__all__ = ["PowerCrust", "compute_poles", "power_crust", "circumcentres"]


def _dot3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot product of ``(..., 3)`` arrays, written out: elementwise IEEE operations only,
    so the result does not depend on the CPU's BLAS kernels (issue 12)."""
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def _compact(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertices used by ``faces`` (indices ``< n_vertices``, ascending) and the faces
    renumbered into them: ``np.unique(faces, return_inverse=True)`` (tests/test_mesh_speed.py)
    by marking instead of sorting."""
    mark = np.zeros(n_vertices, dtype=bool)
    mark[faces] = True
    new_id = np.cumsum(mark) - 1
    return np.flatnonzero(mark), new_id[faces]


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, axis=0, return_index=True, return_inverse=True)[1:]`` for ``(n, 3)`` rows:
    each distinct row's first position, rows in lexicographic order, and each row's index among
    them; the same arrays (tests/test_mesh_speed.py; for floats -0.0 equals 0.0, as there) by a
    stable lexicographic sort, without numpy's structured-dtype sort (several times slower on a
    cloud's 900 poles)."""
    order = np.lexsort((a[:, 2], a[:, 1], a[:, 0]))
    sa = a[order]
    start = np.ones(len(a), dtype=bool)
    start[1:] = np.any(sa[1:] != sa[:-1], axis=1)
    inv = np.empty(len(a), dtype=np.intp)
    inv[order] = np.cumsum(start) - 1
    return order[start], inv


def circumcentres(tets: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Power centres ``(t, 3)`` of tetrahedra ``(t, 4, 3)`` with vertex weights ``(t, 4)``
    (``None`` = circumcentres), and a ``(t,)`` bool flag of the non-degenerate ones.

    The centre ``c`` solves ``2(p_i − p_0)·c = |p_i|² − w_i − |p_0|² + w_0`` for i = 1..3, by
    Cramer's rule with cross products (rows ``r_i``: ``c = Σ b_i (r_j × r_k) / r_1·(r_2 × r_3)``).
    Not ``np.linalg.solve``: LAPACK's rounding differs between OpenBLAS kernel sets, the centres of
    near-flat tetrahedra amplify it, and Qhull's hull of the poles then changed its faces
    (Haswell vs Sandybridge, ``bash .ci/reproduce-cpus.sh``).
    """
    # compiled (mesh/crustfaces.py), the same IEEE operations in the same order as the numpy
    # version it replaced (tests/test_mesh_speed.py: same bits as Cramer's rule on the rows)
    return power_centres(tets, weights)


def _group_first(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct key, the position of the largest value (the first one on ties):
    ``(unique_keys, positions)``, what sorting by key and decreasing value and taking each key's
    first entry gives (tests/test_mesh_speed.py). For non-negative integer keys and values
    without NaN by two unbuffered ``ufunc.at`` passes (0.3 ms instead of the sort's 2.1 ms on
    the 14 000 entries of a table3 cloud's poles, median of 200); otherwise by that sort (NaN
    ranks last)."""
    keys = np.asarray(keys)
    if len(keys) == 0 or keys.dtype.kind not in "iu" or keys.min() < 0 or np.isnan(values).any():
        order = np.lexsort((-values, keys))
        uk, first = np.unique(keys[order], return_index=True)
        return uk, order[first]
    n_keys = int(keys.max()) + 1
    best = np.full(n_keys, -np.inf)
    np.maximum.at(best, keys, values)
    cand = np.flatnonzero(values == best[keys])  # every key has one: its largest value
    pos = np.full(n_keys, len(keys))
    np.minimum.at(pos, keys[cand], cand)
    uk = np.flatnonzero(pos < len(keys))
    return uk.astype(keys.dtype), pos[uk]


def compute_poles(samples: np.ndarray, box_factor: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poles of the samples ``(n, 3)`` (metres).

    Returns ``(poles (m, 3), radii (m,), owner (m,))``: each sample contributes its positive pole
    and, when it exists, its negative pole; ``owner`` is the sample index of each pole, positive
    poles first (``poles[:n]``, in sample order).
    """
    s = np.asarray(samples, dtype=np.float64)
    n = len(s)
    if n < 5:
        raise NirspiError(f"power crust: needs at least 5 points, got {n}")
    lo, hi = s.min(axis=0), s.max(axis=0)
    centre, ext = 0.5 * (lo + hi), max(float(np.max(hi - lo)), 1e-9)
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    pts = np.vstack([s, centre + box_factor * ext * corners])
    try:
        tri = Delaunay(pts, qhull_options="Qbb Qc Q12 QJ")
    except QhullError as exc:
        raise NirspiError(f"power crust: Delaunay failed ({str(exc).splitlines()[0]})") from None
    cc, ok = circumcentres(pts[tri.simplices])
    rad = np.linalg.norm(cc - pts[tri.simplices[:, 0]], axis=1)
    ok &= rad < 50.0 * box_factor * ext  # slivers: circumcentre at "infinity"
    tet = np.repeat(np.arange(len(cc)), 4)
    v = tri.simplices.ravel()
    sel = (v < n) & ok[tet]
    tet, v = tet[sel], v[sel]
    to_cc = cc[tet] - s[v]  # sample -> Voronoi vertex
    dist = np.linalg.norm(to_cc, axis=1)
    owners, pos = _group_first(v, dist)
    if len(owners) != n:
        raise NirspiError("power crust: some samples have no Voronoi vertex (duplicate points?)")
    plus = cc[tet[pos]]
    dirp = plus - s
    side = np.einsum("ij,ij->i", to_cc, dirp[v])
    neg = side < 0
    own_n, pos_n = _group_first(v[neg], dist[neg])
    minus = cc[tet[neg][pos_n]]
    poles = np.vstack([plus, minus])
    owner = np.concatenate([np.arange(n), own_n])
    radii = np.linalg.norm(poles - s[owner], axis=1)
    return poles, radii, owner


def _label_view(poles: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Inner (True) / outer labels by visibility from the camera at the origin (see module)."""
    sz = np.maximum(samples[:, 2], 1e-12)
    uv = samples[:, :2] / sz[:, None]
    tree = cKDTree(uv)
    d_nn, _ = tree.query(uv, k=2)
    rho = 1.5 * float(np.median(d_nn[:, 1]))
    inner = np.zeros(len(poles), dtype=bool)
    front = poles[:, 2] > 0
    puv = poles[front, :2] / poles[front, 2:3]
    d, j = tree.query(puv, k=1)
    behind = np.linalg.norm(poles[front], axis=1) > np.linalg.norm(samples[j], axis=1)
    inner[front] = (d <= rho) & behind
    return inner


def _label_amenta(
    poles: np.ndarray, radii: np.ndarray, pairs: np.ndarray, samples: np.ndarray, edges: np.ndarray
) -> np.ndarray:
    """Inner (True) / outer labels by Amenta et al.'s priority-queue propagation. ``pairs`` is
    ``(q, 3)``: the two pole indices of each sample that has both, and the sample index."""
    m = len(poles)
    nbr: list[list[tuple[int, float, bool]]] = [[] for _ in range(m)]  # (other, certainty, same?)
    for a, b, o in pairs:
        if a == b:
            continue
        u, w = poles[a] - samples[o], poles[b] - samples[o]
        cos = float(_dot3(u, w) / max(np.linalg.norm(u) * np.linalg.norm(w), 1e-300))
        nbr[a].append((int(b), -cos, False))
        nbr[b].append((int(a), -cos, False))
    if len(edges):
        a, b = edges[:, 0], edges[:, 1]
        d2 = np.sum((poles[a] - poles[b]) ** 2, axis=1)
        cos = (radii[a] ** 2 + radii[b] ** 2 - d2) / np.maximum(2 * radii[a] * radii[b], 1e-300)
        for i, j, c in zip(a[cos > 0], b[cos > 0], cos[cos > 0]):
            nbr[i].append((int(j), float(c), True))
            nbr[j].append((int(i), float(c), True))
    label = np.full(m, -1, dtype=np.int8)  # 1 inner, 0 outer
    p_in, p_out = np.zeros(m), np.zeros(m)
    heap: list[tuple[float, int]] = []
    try:
        hull = ConvexHull(poles, qhull_options="QJ").vertices
    except QhullError:
        hull = np.array([int(np.argmax(radii))])
    for h in hull:
        p_out[h] = 2.0  # certain
        heapq.heappush(heap, (-2.0, int(h)))
    for i in range(m):
        heapq.heappush(heap, (0.0, i))
    while heap:
        negp, i = heapq.heappop(heap)
        if label[i] >= 0 or -negp < max(p_in[i], p_out[i]) - 1e-15:
            continue  # stale entry
        lab = 1 if p_in[i] > p_out[i] else 0
        label[i] = lab
        for j, c, same in nbr[i]:
            if label[j] >= 0:
                continue
            to_in = (lab == 1) == same
            if to_in and c > p_in[j]:
                p_in[j] = c
            elif not to_in and c > p_out[j]:
                p_out[j] = c
            else:
                continue
            heapq.heappush(heap, (-max(p_in[j], p_out[j]), j))
    return label == 1


def power_crust(
    samples: np.ndarray,
    labelling: str = "view",
    box_factor: float = 3.0,
    weld_factor: float = 0.25,
    spacing_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Power crust of ``samples`` ``(n, 3)`` (metres).

    Power-diagram vertices closer than ``weld_factor`` × the median sample spacing are welded,
    and each power face (a polygon) is triangulated around its centroid. ``spacing_m``: that
    spacing (metres, :func:`~nirspi_pipe.mesh.remesh.sample_spacing` of ``samples``) when the
    caller has it; None computes it.

    Returns ``(vertices (v, 3) metres, faces (f, 3), info)``; faces are oriented from the inner
    to the outer pole (outward normals).
    """
    s = _usable_samples(samples)
    # A cloud far from the camera for its size (a board 1000 km away) is moved to its centre for
    # Qhull, whose precision checks refuse coordinates 1e7 times the extent; the view labelling
    # still sees the camera at the origin. Clouds nearer than FAR_EXTENTS extents (every scene of
    # the project) are not moved: their arithmetic, and so their meshes, stay bit for bit.
    lo, hi = s.min(axis=0), s.max(axis=0)
    origin = 0.5 * (lo + hi)
    if float(np.max(np.abs(origin))) <= FAR_EXTENTS * max(float(np.max(hi - lo)), 1e-300):
        origin = np.zeros(3)
    view = s
    if labelling == "view" and not bool(np.all(view[:, 2] > 0)):
        behind = int(np.sum(~(view[:, 2] > 0)))
        raise NirspiError(
            f"power crust: labelling 'view' sees the points from the camera at the origin, but {behind} of the "
            f"{len(view)} points are not in front of it (z <= 0)"
        )
    s = s - origin
    poles, radii, owner = compute_poles(s, box_factor)
    # merge coincident poles (e.g. all inner poles of an exact sphere sit at its centre): they
    # would make the regular triangulation degenerate
    n = len(s)
    tol = 1e-9 * max(float(np.ptp(s, axis=0).max()), 1e-12)
    first, inv = _unique_rows(np.round(poles / tol).astype(np.int64))
    merged_r = np.zeros(len(first))
    np.maximum.at(merged_r, inv, radii)
    poles, radii = poles[first], merged_r
    n_minus = len(owner) - n
    pairs = np.column_stack([inv[owner[n:]], inv[n:], owner[n:]]) if n_minus else np.zeros((0, 3), np.int64)
    # a tiny deterministic joggle (1e-7 of the extent) of the poles, used consistently for the
    # hull and the power centres, avoids degenerate (flat) regular tetrahedra
    ext = max(float(np.ptp(s, axis=0).max()), 1e-12)
    poles = poles + np.random.default_rng(0).normal(0.0, 1e-7 * ext, poles.shape)
    lifted = np.column_stack([poles, np.sum(poles**2, axis=1) - radii**2])
    try:
        hull = ConvexHull(lifted, qhull_options="Qt")
    except QhullError as exc:
        raise NirspiError(f"power crust: power diagram failed ({str(exc).splitlines()[0]})") from None
    lower = hull.equations[:, 3] < 0
    tets = hull.simplices[lower]  # regular triangulation of the poles
    centres, ok = circumcentres(poles[tets], (radii**2)[tets])
    tets, centres = tets[ok], centres[ok]
    # the six edges of each tetrahedron, with the two other vertices (the ring around the edge)
    edge_sel = np.array([(0, 1, 2, 3), (0, 2, 1, 3), (0, 3, 1, 2), (1, 2, 0, 3), (1, 3, 0, 2), (2, 3, 0, 1)])
    if labelling == "view":
        inner = _label_view(poles + origin, view)
    else:
        ends = tets[:, edge_sel[:, :2]].reshape(-1, 2)
        inner = _label_amenta(poles, radii, pairs, s, np.unique(np.sort(ends, axis=1), axis=0))
    # the faces between inner and outer poles' cells, welded and triangulated (compiled)
    spacing = float(np.median(cKDTree(s).query(s, k=2)[0][:, 1])) if spacing_m is None else float(spacing_m)
    wtol = max(weld_factor * spacing, 1e-7 * max(float(np.ptp(s, axis=0).max()), 1e-12))
    verts, faces, n_poly = crust_faces(poles, tets, centres, inner, wtol)
    if len(faces) == 0:
        raise NirspiError(
            f"power crust: no face between inner and outer poles ({int(inner.sum())} of {len(poles)} poles "
            f"labelled inner by labelling {labelling!r}): too few points, or one far from the others"
        )
    m = len(poles)
    info = {"poles": int(m), "inner_poles": int(inner.sum()), "power_faces": int(n_poly)}
    return verts + origin, faces, info


def _usable_samples(samples: np.ndarray) -> np.ndarray:
    """``samples`` ``(n, 3)`` without exact duplicates (first of each kept, order kept: a cloud
    without duplicates is returned as it is), or :class:`NirspiError` in one line when no surface
    can be made of them: fewer than 5 distinct points, or all of them on one line."""
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3:
        raise NirspiError(f"power crust: needs points of shape (n, 3), got {s.shape}")
    if len(s):
        first, _ = _unique_rows(s)
        if len(first) < len(s):
            s = s[np.sort(first)]
    if len(s) < 5:
        given = len(np.asarray(samples))
        raise NirspiError(
            f"power crust: needs at least 5 distinct points, got {len(s)}"
            + (f" ({given} given; points within the {CLOUD_QUANTUM_M:g} m grid are one)" if given != len(s) else "")
        )
    sv = np.linalg.svd(s - s.mean(axis=0), compute_uv=False)
    if sv[1] <= COLLINEAR_REL * sv[0]:
        raise NirspiError(f"power crust: the {len(s)} points lie on one line; no surface passes through them")
    return s


@lru_cache(maxsize=1)
def warm_up() -> bool:
    """Run :func:`power_crust` once on a small cloud (a noisy cap of a sphere seen from the
    origin), so that its compiled kernels are compiled or loaded from numba's on-disk cache in
    the stage's build, never in a timed surface stage. Once per process."""
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.linspace(-0.4, 0.4, 7), np.linspace(-0.4, 0.4, 7))
    pts = np.column_stack([u.ravel(), v.ravel(), 2.0 - np.sqrt(1.0 - u.ravel() ** 2 - v.ravel() ** 2)])
    pts += rng.normal(0.0, 1e-3, pts.shape)

    try:  # a numba cache that does not load is rebuilt once, with a warning naming it
        rebuild_on_failure(lambda: power_crust(pts, "view"), what="the power crust", kernels=("crustfaces",))
    except NirspiError:
        return False
    return True


def trim_to_samples(
    vertices: np.ndarray, faces: np.ndarray, samples: np.ndarray, factor: float, spacing_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the faces whose three vertices lie within ``factor`` × the median sample spacing of
    some sample; drop unused vertices. Metres in, metres out. ``spacing_m``: that spacing
    (metres, :func:`~nirspi_pipe.mesh.remesh.sample_spacing` of ``samples``) when the caller has
    it; None computes it."""
    tree = cKDTree(samples)
    spacing = float(np.median(tree.query(samples, k=2)[0][:, 1])) if spacing_m is None else float(spacing_m)
    d, _ = tree.query(vertices, k=1)
    near = d <= factor * spacing
    keep = near[faces].all(axis=1)
    faces = faces[keep]
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    used, inv = _compact(faces, len(vertices))
    return vertices[used], inv


@dataclass(frozen=True)
class PowerCrust:
    """Surface ``power_crust`` (Amenta, Choi & Kolluri 2001) on scipy.spatial's Qhull.

    Attributes:
        labelling: ``view`` (one-sided depth data, camera at the origin) or ``amenta``
            (closed, well-sampled point sets).
        closed: keep the whole closed power crust (True) or only the part near the samples.
        trim_factor: with ``closed: false``, the distance to the nearest sample, in median sample
            spacings, beyond which a face is dropped.
        box_factor: half-size of the bounding box added to bound the Voronoi cells, in units of
            the samples' extent.
        weld_factor: power-diagram vertices closer than this × the median sample spacing are
            merged (removes the slivers of near-degenerate power faces); 0 = exact coincidences only.
            When the mesh is remeshed, at least half the remesher's target edge, and at most half
            the sample spacing (``0.5 × min(remesh_edge_factor, 1)``; coarser welding would merge
            across the crust's own polygons): the remesher collapses every edge shorter than 0.8 of
            its target anyway, one by one with its checks; welding them first is cheaper, and on the
            16 Table 6 jobs it left the mean skewness and the chamfer distance as they were
            (docs/mesh.md).
        remesh_iterations: rounds of isotropic remeshing after clean-up
            (:func:`~nirspi_pipe.mesh.remesh.clean_and_remesh`); 0 = clean-up only.
        remesh_edge_factor: target edge length, × the cloud's median sample spacing.
        max_hole_edges: clean-up closes holes bounded by at most this many edges (0 = none).
        remesher: ``auto`` (``compiled`` where numba compiles it, else ``pymeshlab``),
            ``compiled`` (:mod:`nirspi_pipe.mesh.isotropic`) or ``pymeshlab``; the record's
            ``info.surface.remesher`` says which ran.
    """

    labelling: Annotated[str, OneOf(("view", "amenta"))] = "view"
    closed: bool = False
    trim_factor: Annotated[float, Range(0.0, None, "a factor", lo_open=True)] = 1.5
    remesh_iterations: RemeshIterations = 3
    remesh_edge_factor: RemeshEdgeFactor = 1.0
    max_hole_edges: MaxHoleEdges = 30
    box_factor: Annotated[float, Range(1.5, None, "a factor")] = 3.0
    remesher: Remesher = "auto"
    # Not in the generated config schema (never a key of surface=power_crust; +surface.weld_factor=…
    # sets it): the configs, job keys and derived seeds of power-crust runs stay as they were.
    weld_factor: Annotated[float, Range(0.0, 1.0, "a fraction of the sample spacing", hi_open=True)] = field(
        default=0.25, metadata={"config": False}
    )

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Load the crust's and the remesher's compiled kernels (numba's disk cache, or one
        compilation of ~20 s when it is cold: once, not by every job at the same time), pymeshlab
        and the mesh writers (:class:`nirspi_pipe.stages.WarmsUp`)."""
        resolve_remesher(str(params.get("remesher", cls.remesher)))
        load_meshlab()
        warm_up()
        warm_up_outputs()

    def __post_init__(self) -> None:
        check_ranges(self)  # before any compilation: a bad key is refused at once
        # compile (or load from numba's cache) the crust's kernels and the remesher now, at build,
        # never inside the timed stage
        object.__setattr__(self, "_remesher", resolve_remesher(self.remesher))
        warm_up()

    def reconstruct(self, cloud: PointCloud) -> Mesh:
        """Power-crust mesh of ``cloud.points_m`` (metres)."""
        pts = np.asarray(cloud.points_m, dtype=np.float64)
        if not np.all(np.isfinite(pts)):
            raise NirspiError("power crust: the point cloud has non-finite points")
        pts = _usable_samples(np.round(pts / CLOUD_QUANTUM_M) * CLOUD_QUANTUM_M)  # duplicates dropped
        spacing = sample_spacing(pts)  # once: the crust's welding, the trim and the remeshing use it
        weld = self.weld_factor
        if self.remesh_iterations > 0:
            weld = max(weld, 0.5 * min(self.remesh_edge_factor, 1.0))
        verts, faces, info = power_crust(pts, self.labelling, self.box_factor, weld, spacing)
        info["faces_closed"] = int(len(faces))
        if not self.closed:
            verts, faces = trim_to_samples(verts, faces, pts, self.trim_factor, spacing)
            if len(faces) == 0:
                raise NirspiError(
                    f"power crust: no face lies near the {len(pts)} points after trimming (too few or too "
                    "scattered for a surface)"
                )
        remesher = self._remesher  # type: ignore[attr-defined]
        verts, faces, rinfo = remesh_to_cloud(
            verts, faces, pts, self.remesh_iterations, self.remesh_edge_factor, self.max_hole_edges, spacing, remesher
        )
        if len(faces) == 0:
            raise NirspiError(
                f"power crust: the clean-up left no face of the crust of the {len(pts)} points (too few or too "
                "scattered for a surface)"
            )
        info.update(rinfo)
        info["faces"] = int(len(faces))
        info["remesher"] = remesher
        covered = cloud_coverage(verts, faces, pts, spacing)
        info["cloud_covered_fraction"] = covered
        if covered < MIN_COVERED_FRACTION:
            warnings.warn(
                f"power crust: the mesh lies near only {covered:.0%} of the {len(pts)} cloud points (within "
                f"{COVERAGE_SPACINGS:g} sample spacings): it lost most of the shape (issue 44; "
                "info.surface.cloud_covered_fraction)",
                stacklevel=3,
            )
        return Mesh(vertices_m=verts, faces=faces.astype(np.int64), info=info)
