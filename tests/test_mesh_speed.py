"""The fast helpers of the 3D path give the same bits as the straightforward numpy they replace
(power crust bookkeeping, fusion's heat filter): the speed-up must not change any mesh or cloud."""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy import sparse
from scipy.spatial import cKDTree

from nirspi_pipe.mesh.anchors import _anchor_residuals, _dots, np_sum
from nirspi_pipe.mesh.crustfaces import _stable_order, _weld
from nirspi_pipe.mesh.pointcloud import _nanmedian_last, _step_matrix, heat_diffusion, heat_graph, heat_step
from nirspi_pipe.mesh.powercrust import (
    COVERAGE_SPACINGS,
    _compact,
    _group_first,
    _unique_rows,
    circumcentres,
    cloud_coverage,
)

# finite values with ties, signed zeros and a wide range of magnitudes
_FLOATS = st.one_of(
    st.sampled_from([0.0, -0.0, 1.0, -1.0, 0.5]), st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=True)
)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal values, dtypes and shapes, with NaN equal to NaN and -0.0 distinct from +0.0."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 30), st.data())
def test_compact_is_unique_inverse(n: int, data: st.DataObject) -> None:
    faces = data.draw(hnp.arrays(np.int64, (data.draw(st.integers(0, 15)), 3), elements=st.integers(0, n - 1)))
    used, inv = _compact(faces, n)
    ref_used, ref_inv = np.unique(faces, return_inverse=True)
    assert _same(used, ref_used) and _same(inv, ref_inv.reshape(-1, 3))


def _group_first_reference(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((-values, keys))
    uk, first = np.unique(keys[order], return_index=True)
    return uk, order[first]


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 40).flatmap(
        lambda k: st.tuples(
            hnp.arrays(np.int32, k, elements=st.integers(-2, 6)),
            hnp.arrays(
                np.float64, k, elements=st.one_of(_FLOATS, st.sampled_from([np.inf, -np.inf, np.nan, 2.0, 2.0]))
            ),
        )
    )
)
def test_group_first_is_the_sort(kv: tuple[np.ndarray, np.ndarray]) -> None:
    keys, values = kv
    uk, pos = _group_first(keys, values)
    ref_uk, ref_pos = _group_first_reference(keys, values)
    assert _same(uk, ref_uk) and np.array_equal(pos, ref_pos)


def _circumcentres_reference(tets: np.ndarray, weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Cramer's rule on the (t, 4, 3) rows with np.cross, as before the speed-up."""
    p0 = tets[:, 0]
    r = 2.0 * (tets[:, 1:] - p0[:, None, :])
    lift = tets[..., 0] * tets[..., 0] + tets[..., 1] * tets[..., 1] + tets[..., 2] * tets[..., 2]
    if weights is not None:
        lift = lift - weights
    b = lift[:, 1:] - lift[:, :1]
    c23, c31, c12 = np.cross(r[:, 1], r[:, 2]), np.cross(r[:, 2], r[:, 0]), np.cross(r[:, 0], r[:, 1])
    det = r[:, 0, 0] * c23[:, 0] + r[:, 0, 1] * c23[:, 1] + r[:, 0, 2] * c23[:, 2]
    scale = np.max(np.abs(r), axis=(1, 2)) ** 3
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-300)
    c = np.zeros((len(tets), 3))
    if ok.any():
        num = b[ok, 0:1] * c23[ok] + b[ok, 1:2] * c31[ok] + b[ok, 2:3] * c12[ok]
        c[ok] = num / det[ok][:, None]
    return c, ok


@settings(max_examples=100, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(0, 12), st.just(4), st.just(3)), elements=st.floats(-1.0, 1.0)),
    st.booleans(),
    st.booleans(),
)
def test_circumcentres_is_cramer_on_rows(tets: np.ndarray, weighted: bool, flatten_one: bool) -> None:
    if flatten_one and len(tets):  # a degenerate (flat) tetrahedron next to regular ones
        tets[0, 3] = tets[0, 0] + 0.5 * (tets[0, 1] - tets[0, 0]) + 0.5 * (tets[0, 2] - tets[0, 0])
    weights = np.abs(tets[..., 0]) * 0.1 if weighted else None
    c, ok = circumcentres(tets, weights)
    ref_c, ref_ok = _circumcentres_reference(tets, weights)
    assert _same(c, ref_c) and _same(ok, ref_ok)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(5, 60), st.sampled_from([1.0, 3.0, 0.01]))
def test_heat_step_on_a_reused_graph_is_heat_diffusion(seed: int, p: int, t: float) -> None:
    pts = np.random.default_rng(seed).normal(0.0, 0.01, (p, 3)) + [0.0, 0.0, 0.2]
    graph = heat_graph(pts, 8)
    r = np.linalg.norm(pts, axis=1)
    for values in (r, pts, r):  # the graph serves several solves unchanged
        assert _same(heat_step(values, *graph, t), heat_diffusion(values, pts, 8, t))
    # ItofFusion._diffuse differs from before only by this substitution (one graph, three steps)


@settings(max_examples=150, deadline=None)
@given(
    hnp.arrays(
        np.float64,
        st.tuples(st.integers(0, 6), st.integers(1, 9)),
        elements=st.one_of(st.floats(-1e300, 1e300), st.sampled_from([np.nan, np.nan, np.inf, -np.inf, 1.5, 1.5])),
    )
)
def test_nanmedian_last_is_np_nanmedian(a: np.ndarray) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows
        ref = np.nanmedian(a, axis=-1)
    assert np.array_equal(_nanmedian_last(a), ref, equal_nan=True)


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 12), st.lists(st.tuples(st.integers(0, 11), st.integers(0, 11)), max_size=60))
def test_stable_order_is_a_stable_argsort(m: int, pairs: list[tuple[int, int]]) -> None:
    """The power crust groups its mixed edges by key ``a*m + b`` with a counting sort: the same
    permutation as numpy's stable argsort (equal keys keep their order)."""
    key = np.array([(a % m) * m + (b % m) for a, b in pairs], dtype=np.int64)
    assert np.array_equal(_stable_order(key, m), np.argsort(key, kind="stable"))


@settings(max_examples=100, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)), elements=st.floats(-1.0, 1.0)),
    st.floats(0.01, 0.8),
)
def test_weld_is_the_components_of_the_close_pairs(points: np.ndarray, tol: float) -> None:
    """Welding = connected components of the pairs within ``tol`` (what cKDTree.query_pairs and
    scipy's connected_components give, as the numpy crust did), each cluster at its members' mean."""
    from hypothesis import assume
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree
    from scipy.spatial.distance import pdist

    # a distance within rounding of tol may fall either side (squared vs rooted comparison)
    assume(not np.any(np.abs(pdist(points) - tol) < 1e-12))
    cl, pos = _weld(np.ascontiguousarray(points), tol)
    close = cKDTree(points).query_pairs(tol, output_type="ndarray")
    graph = coo_matrix((np.ones(len(close)), (close[:, 0], close[:, 1])), shape=(len(points),) * 2)
    _, ref = connected_components(graph, directed=False)
    # the same partition (labels may be numbered differently)
    assert len(set(zip(cl.tolist(), ref.tolist()))) == len(set(cl.tolist())) == len(set(ref.tolist()))
    for c in range(len(pos)):
        assert np.allclose(pos[c], points[cl == c].mean(axis=0), rtol=0, atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(st.lists(_FLOATS, max_size=300))
def test_np_sum_is_numpys_sum(values: list[float]) -> None:
    # the anchors' fit sums Python floats in numpy's order: same bits as np.sum of the array
    # (lengths past 8 and 128 exercise numpy's eight running sums and its halving)
    ours = np_sum(values)
    ref = float(np.sum(np.array(values, dtype=np.float64)))
    assert np.float64(ours).tobytes() == np.float64(ref).tobytes()
    other = values[::-1]  # the fit's dot products (a plain loop below 8 terms)
    ref_dot = float(np.sum(np.array(values, dtype=np.float64) * np.array(other, dtype=np.float64)))
    assert np.float64(_dots(values, other)).tobytes() == np.float64(ref_dot).tobytes()


def _residuals_reference(b, z, sig, focal, sp, prior, x):  # type: ignore[no-untyped-def]
    """The anchors' residuals as numpy arrays (the code the Python-float version replaced)."""
    eu, c = np.exp(x[0]), np.exp(x[1])
    rel = focal is not None
    s = eu * (c / focal if rel else 1.0)
    r, du, dv = [(c + s * b - z) / sig], [s * b / sig], [(c + s * b if rel else c + 0.0 * b) / sig]
    if sp is not None:
        r.append(np.array([np.expm1(x[0]) / sp]))
        du.append(np.array([eu / sp]))
        dv.append(np.zeros(1))
    if prior is not None:
        r.append(np.array([(c - prior[0]) / prior[1]]))
        du.append(np.zeros(1))
        dv.append(np.array([c / prior[1]]))
    return np.concatenate(r), np.concatenate(du), np.concatenate(dv)


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 12),
    st.sampled_from([None, 300.0]),
    st.sampled_from([None, 0.2]),
    st.sampled_from([None, (0.2, 0.05)]),
)
def test_anchor_residuals_are_the_numpy_ones(seed: int, k: int, focal, sp, prior) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    b = rng.normal(0.0, 10.0 ** rng.uniform(-2, 2), k)
    z = 0.2 + rng.normal(0.0, 0.01, k)
    sig = 10.0 ** rng.uniform(-5, -1, k)
    fun = _anchor_residuals(b, z, sig, focal, sp, prior)
    for x in ((0.0, np.log(0.2)), tuple(rng.normal(0.0, 1.0, 2))):
        ours = fun((float(x[0]), float(x[1])))
        for got, ref in zip(ours, _residuals_reference(b, z, sig, focal, sp, prior, x)):
            assert _same(np.array(got, dtype=np.float64), ref)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 80), st.integers(1, 10), st.sampled_from([5e-324, 0.3, 2.0]))
def test_step_matrix_is_scipys(seed: int, p: int, knn: int, t: float) -> None:
    # the heat step's matrix (1 + t) D - t W, built without scipy's conversions: same stored
    # entries in the same order (duplicate points put W's entries on the diagonal; t = 5e-324
    # makes t * w underflow to zeros, which scipy does not store)
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, 0.01, (p, 3))
    pts[: p // 3] = pts[0]
    w, deg = heat_graph(pts, knn)
    ref = ((1.0 + t) * sparse.diags(deg) - t * w).tocsc()
    data, indices, indptr = _step_matrix(w, deg, t)
    assert _same(data, ref.data) and np.array_equal(indices, ref.indices) and np.array_equal(indptr, ref.indptr)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 40), st.data())
def test_unique_rows_is_numpys_unique(n: int, data: st.DataObject) -> None:
    # integer rows (the merged poles) and float rows with ties and signed zeros (the samples)
    ints = data.draw(hnp.arrays(np.int64, (n, 3), elements=st.integers(-3, 3)))
    floats = data.draw(hnp.arrays(np.float64, (n, 3), elements=st.sampled_from([0.0, -0.0, 1.0, -2.5, 1e-300])))
    for a in (ints, floats):
        first, inv = _unique_rows(a)
        _, ref_first, ref_inv = np.unique(a, axis=0, return_index=True, return_inverse=True)
        assert np.array_equal(first, ref_first) and np.array_equal(inv, ref_inv.ravel())


def _coverage_reference(verts: np.ndarray, faces: np.ndarray, pts: np.ndarray, spacing: float) -> float:
    """cloud_coverage as one search over all samples (vertices, edge midpoints, centroids)."""
    tri = verts[faces]
    mids = 0.5 * (tri + np.roll(tri, -1, axis=1))
    samples = np.concatenate([tri.reshape(-1, 3), mids.reshape(-1, 3), tri.mean(axis=1)])
    edge = float(np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=-1).max())
    dist, _ = cKDTree(samples).query(pts, k=1)
    return float(np.mean(dist <= COVERAGE_SPACINGS * spacing + 0.5 * edge))


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(1, 200), st.floats(0.0, 0.5))
def test_cloud_coverage_searches_vertices_first_with_the_same_result(seed: int, nf: int, npts: int, sp: float) -> None:
    # a point near an edge midpoint or a centroid but no vertex must still count (small spacing)
    rng = np.random.default_rng(seed)
    verts = rng.uniform(-1.0, 1.0, (nf + 2, 3))
    faces = np.array([rng.choice(nf + 2, 3, replace=False) for _ in range(nf)])
    pts = np.concatenate([rng.uniform(-2.0, 2.0, (npts, 3)), verts[faces].mean(axis=1)])
    assert cloud_coverage(verts, faces, pts, sp) == _coverage_reference(verts, faces, pts, sp)
