"""The compiled clean-up and isotropic remesher (mesh/isotropic.py) and the compiled power-crust
faces (mesh/crustfaces.py): manifold output on hostile face lists, the surface kept, shapes
improved, bounded growth, and clear errors. Its agreement with pymeshlab's remesher is in the parity
harness (tests/test_parity.py, family ``remesh``)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.mesh.isotropic import clean_and_remesh_compiled, remesh_clean
from nirspi_pipe.mesh.meshclean import clean_mesh
from nirspi_pipe.mesh.metrics3d import equiangle_skewness
from nirspi_pipe.mesh.powercrust import power_crust, trim_to_samples
from nirspi_pipe.mesh.remesh import resolve_remesher, sample_spacing


def _edges(faces: np.ndarray) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """Undirected edge -> list of (face, direction sign) using it."""
    out: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for fi, f in enumerate(faces):
        for k in range(3):
            a, b = int(f[k]), int(f[(k + 1) % 3])
            out.setdefault((min(a, b), max(a, b)), []).append((fi, 1 if a < b else -1))
    return out


def assert_manifold(vertices: np.ndarray, faces: np.ndarray) -> None:
    """Edge-manifold and consistently oriented (an edge has one face, or two that run it in opposite
    directions), vertex-manifold (a vertex's faces form one fan), no degenerate or repeated face."""
    f = np.asarray(faces)
    if len(f) == 0:
        return
    assert f.min() >= 0 and f.max() < len(vertices)
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f), "duplicate faces"
    edges = _edges(f)
    for users in edges.values():
        assert len(users) <= 2
        if len(users) == 2:
            assert users[0][1] != users[1][1], "two faces run an edge the same way"
    # one fan per vertex: the faces around v, linked through the edges at v they share
    by_vertex: dict[int, list[int]] = {}
    for fi, fc in enumerate(f):
        for v in fc:
            by_vertex.setdefault(int(v), []).append(fi)
    for v, fs in by_vertex.items():
        parent = {x: x for x in fs}

        def find(x: int) -> int:
            while parent[x] != x:
                x = parent[x]
            return x

        for (a, b), users in edges.items():
            if v in (a, b) and len(users) == 2 and users[0][0] in parent and users[1][0] in parent:
                parent[find(users[0][0])] = find(users[1][0])
        assert len({find(x) for x in fs}) == 1, f"vertex {v} joins several fans"


def _cap_cloud(n: int = 14, noise: float = 2e-5, seed: int = 0) -> np.ndarray:
    """A noisy spherical cap (radius 25 mm, 0.2 m from the camera at the origin), metres."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-0.7, 0.7, n), np.linspace(-0.7, 0.7, n))
    keep = u**2 + v**2 < 0.6
    u, v = u[keep], v[keep]
    pts = 0.025 * np.column_stack([u, v, -np.sqrt(1.0 - u**2 - v**2)]) + [0.0, 0.0, 0.2]
    return pts + rng.normal(0.0, noise, pts.shape)


def _crust_sheet(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    sp = sample_spacing(pts)
    v, f, _ = power_crust(pts, "view", 3.0, 0.25, sp)
    v, f = trim_to_samples(v, f, pts, 1.5, sp)
    return v, f, sp


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n_vertices=st.integers(3, 12),
    data=st.data(),
)
def test_clean_mesh_turns_any_face_list_into_a_manifold(n_vertices: int, data: st.DataObject) -> None:
    """Hostile face lists: repeated and flipped faces, edges of three or more faces, fans touching at
    a vertex, degenerate and zero-area faces, duplicate vertex positions."""
    coords = data.draw(
        st.lists(st.tuples(*[st.integers(0, 3)] * 3), min_size=n_vertices, max_size=n_vertices), label="coords"
    )
    faces = data.draw(
        st.lists(st.tuples(*[st.integers(0, n_vertices - 1)] * 3), min_size=1, max_size=30), label="faces"
    )
    v = np.asarray(coords, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cv, cf, _ = clean_mesh(v, f, max_hole_edges=data.draw(st.sampled_from([0, 3, 30])), min_component_faces=0)
    assert_manifold(cv, cf)
    # only merges and removals: every output vertex is an input position
    assert all(any(np.array_equal(p, q) for q in v) for p in cv)


def test_remesher_keeps_the_surface_improves_the_shapes_and_sizes_the_edges() -> None:
    pts = _cap_cloud()
    v, f, sp = _crust_sheet(pts)
    before = equiangle_skewness(v, f).mean()
    cv, cf, _ = clean_mesh(v, f)
    ov, of = remesh_clean(cv, cf, sp, 3)
    assert_manifold(ov, of)
    after = equiangle_skewness(ov, of)
    assert after.mean() < 0.6 * before and after.mean() < 0.3, (before, after.mean())
    # the sphere: every vertex stays within a tenth of the spacing of it (relaxation is tangential)
    r = np.linalg.norm(ov - [0.0, 0.0, 0.2], axis=1)
    r_in = np.linalg.norm(v - [0.0, 0.0, 0.2], axis=1)
    assert np.abs(r - 0.025).max() < np.abs(r_in - 0.025).max() + 0.1 * sp
    lengths = np.linalg.norm(ov[of] - ov[np.roll(of, 1, axis=1)], axis=2).ravel()
    assert np.mean((lengths > 0.5 * sp) & (lengths < 1.5 * sp)) > 0.9


def test_remesher_is_deterministic_and_leaves_tiny_meshes_alone() -> None:
    pts = _cap_cloud(10, seed=5)
    v, f, sp = _crust_sheet(pts)
    a = clean_and_remesh_compiled(v, f, sp, 3)
    b = clean_and_remesh_compiled(v, f, sp, 3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    one = np.array([[0, 1, 2]])
    tri = np.eye(3)
    assert np.array_equal(clean_and_remesh_compiled(tri, one, 0.1, 3)[1], one)
    assert len(clean_and_remesh_compiled(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.1, 3)[1]) == 0


def test_holes_up_to_the_limit_are_closed_and_the_outer_border_stays_open() -> None:
    n = 9
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    f = f[np.all(f != idx[4, 4], axis=1)]  # a hole of 6 border edges around the centre
    cv, cf, info = clean_mesh(v, f, max_hole_edges=30)
    assert info["faces_hole_fill"] == 4 and info["holes_not_closed"] == 0
    border = [e for e, users in _edges(cf).items() if len(users) == 1]
    assert len(border) == 4 * (n - 1)  # only the outer border (32 edges > 30)
    assert_manifold(cv, cf)


def test_remesher_refuses_an_explosion_with_a_clear_error() -> None:
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 3], [0, 3, 2]])
    with pytest.raises(NirspiError, match="remesh_edge_factor"):
        remesh_clean(v, f, 1e-4, 1)  # 1 m² at 0.1 mm edges: ~10⁸ faces, above MAX_FACES


def test_remesher_key_is_checked() -> None:
    with pytest.raises(ConfigError, match="auto, compiled, pymeshlab"):
        resolve_remesher("meshlab")
    assert resolve_remesher("auto") == "compiled"
    assert resolve_remesher("pymeshlab") == "pymeshlab"


@pytest.mark.slow
def test_compiled_kernels_fuse_no_multiply_add(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Same bits on CPUs with and without FMA: without fast-math, LLVM must not contract a*b + c
    into a fused multiply-add (the machine code of every compiled kernel is searched; the cache is
    empty so numba compiles afresh and keeps the assembly). Marked slow: compiling every kernel
    from cold takes ~80 s of CPU (CI runs it in its ``pytest -m 'slow and not torch'`` step)."""
    import os
    import subprocess
    import sys

    code = (
        "import re, numpy as np\n"
        "import importlib, nirspi_pipe.mesh.isotropic as iso, nirspi_pipe.mesh.powercrust as pc\n"
        "from nirspi_pipe.mesh.jitcache import KERNEL_MODULES\n"
        "assert iso.warm_up() and pc.warm_up()\n"
        "n = hits = 0\n"
        "for m in [importlib.import_module('nirspi_pipe.mesh.' + k) for k in KERNEL_MODULES]:\n"
        "    for k in dir(m):\n"
        "        d = getattr(m, k)\n"
        "        for sig in getattr(d, 'signatures', []):\n"
        "            n += 1\n"
        "            hits += len(re.findall(r'\\b(v?fn?m(add|sub)\\w*|fml[as])\\b', d.inspect_asm(sig)))\n"
        "print(n, hits)\n"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=600, capture_output=True, text=True)
    n, hits = map(int, out.stdout.split())
    assert n >= 20 and hits == 0, out.stdout


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(3, 9),
    jitter=st.floats(0.0, 0.45),
    bump=st.floats(-2.0, 2.0),
    target=st.floats(0.2, 3.0),
    drop=st.lists(st.integers(0, 200), max_size=25),
    seed=st.integers(0, 2**16),
)
def test_remesher_output_is_a_manifold_on_irregular_grids_with_holes(
    n: int, jitter: float, bump: float, target: float, drop: list[int], seed: int
) -> None:
    """Jittered, folded grids with faces removed (holes, bridges, lone triangles, pieces meeting at a
    vertex) at edge lengths from a fifth to three times the grid step: the clean-up and remeshing
    end in a manifold with finite vertices, every output vertex near the input surface's extent."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    x = x + rng.uniform(-jitter, jitter, x.shape)
    y = y + rng.uniform(-jitter, jitter, y.shape)
    z = bump * np.sin(x) * np.cos(y)
    v = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    f = np.delete(f, [i for i in drop if i < len(f)], axis=0)
    if len(f) == 0:
        return
    # holes of up to 3 edges (a dropped face) are closed; the grid's own border (8 edges or more)
    # stays open: closed over, a flat sheet becomes a zero-volume pillow, which remeshing shrinks
    ov, of, _ = clean_and_remesh_compiled(v, f, target, 3, 1.0, 3, 1)
    assert np.all(np.isfinite(ov))
    assert_manifold(ov, of)
    lo, hi = v.min(axis=0) - 1e-9, v.max(axis=0) + 1e-9
    assert np.all((ov >= lo - abs(bump)) & (ov <= hi + abs(bump)))


def _uv_sphere(n_around: int = 16, n_rings: int = 11, radius: float = 0.025) -> tuple[np.ndarray, np.ndarray]:
    """A closed UV sphere (poles and ``n_rings`` rings of ``n_around`` vertices), faces outward."""
    theta = np.linspace(0.0, np.pi, n_rings + 2)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.column_stack([(np.sin(t) * np.cos(p)).ravel(), (np.sin(t) * np.sin(p)).ravel(), np.cos(t).ravel()])
    v = radius * np.vstack([[0.0, 0.0, 1.0], ring, [0.0, 0.0, -1.0]])
    south = len(v) - 1

    def at(i: int, j: int) -> int:
        return 1 + i * n_around + j % n_around

    faces = [[0, at(0, j), at(0, j + 1)] for j in range(n_around)]
    for i in range(n_rings - 1):
        for j in range(n_around):
            faces += [[at(i, j), at(i + 1, j), at(i + 1, j + 1)], [at(i, j), at(i + 1, j + 1), at(i, j + 1)]]
    faces += [[south, at(n_rings - 1, j + 1), at(n_rings - 1, j)] for j in range(n_around)]
    return v, np.asarray(faces, dtype=np.int64)


def _area(v: np.ndarray, f: np.ndarray) -> float:
    p = v[f]
    return 0.5 * float(np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    p = v[f]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


_SPHERE_V, _SPHERE_F = _uv_sphere()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(flipped=st.lists(st.booleans(), min_size=len(_SPHERE_F), max_size=len(_SPHERE_F)))
def test_a_closed_mesh_with_flipped_faces_keeps_its_surface(flipped: list[bool]) -> None:
    """Any subset of a closed sphere's faces turned over: the clean-up orients every face like the
    majority (the fewer faces are flipped back), and the remeshed sphere keeps ≥ 95 % of its area,
    stays closed and consistently oriented. (Before, edges whose two faces disagreed were cut, the
    cut pieces dropped as small: such a mesh lost every face.)"""
    v, f = _SPHERE_V, _SPHERE_F.copy()
    sel = np.asarray(flipped)
    f[sel] = f[sel][:, ::-1]
    k = int(sel.sum())
    cv, cf, info = clean_mesh(v, f)
    assert len(cf) == len(f) and info["faces_flipped"] == min(k, len(f) - k)
    assert_manifold(cv, cf)
    assert all(len(users) == 2 for users in _edges(cf).values()), "closed: no border edge"
    volume = _signed_volume(v, _SPHERE_F)  # > 0: the sphere's faces point outward
    if 2 * k != len(f):  # the majority's orientation is kept (a tie keeps the first face's)
        assert _signed_volume(cv, cf) == pytest.approx(volume if 2 * k < len(f) else -volume, rel=1e-9)
    ov, of, rinfo = clean_and_remesh_compiled(v, f, 0.005, 3)
    assert rinfo["faces_after_remesh"] == len(of) > 0
    assert _area(ov, of) >= 0.95 * _area(v, _SPHERE_F)
    assert_manifold(ov, of)
    assert all(len(users) == 2 for users in _edges(of).values())
    assert abs(_signed_volume(ov, of)) >= 0.95 * volume


def test_orientation_is_repaired_per_piece_and_a_moebius_strip_stays_manifold() -> None:
    """Two spheres, one with most faces flipped: each piece keeps its own majority. A Möbius strip
    (not orientable) is cut where the walk cannot agree, and is still a manifold."""
    v1, f1 = _uv_sphere()
    f_in = f1.copy()
    f_in[: 3 * len(f1) // 4] = f_in[: 3 * len(f1) // 4, ::-1]  # the second copy: 3/4 flipped
    v = np.vstack([v1, v1 + [0.1, 0.0, 0.0]])
    f = np.vstack([f1, f_in + len(v1)])
    cv, cf, info = clean_mesh(v, f)
    assert info["faces_flipped"] == len(f1) - 3 * len(f1) // 4 and len(cf) == len(f)
    assert_manifold(cv, cf)
    left = cv[cf][:, :, 0].mean(axis=1) < 0.05  # the first sphere (centred at x = 0)
    assert _signed_volume(cv, cf[left]) > 0 > _signed_volume(cv, cf[~left])
    # a Möbius strip of 12 quads: the last quad joins the first with a half twist
    n = 12
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    centre = np.column_stack([np.cos(t), np.sin(t), np.zeros(n)])
    across = np.column_stack([np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)]) * 0.3
    mv = np.vstack([centre + across, centre - across])  # vertex i: one edge, n + i: the other
    mf = []
    for i in range(n):
        j = (i + 1) % n
        a, b, c, d = (i, j, n + j, n + i) if j else (i, n + j, j, n + i)  # the twist swaps the edges
        mf += [[a, b, c], [a, c, d]]
    mcv, mcf, _ = clean_mesh(mv, np.asarray(mf), min_component_faces=0)
    assert len(mcf) >= 2 * n and _area(mcv, mcf) >= 0.99 * _area(mv, np.asarray(mf))
    assert_manifold(mcv, mcf)


def test_pymeshlab_path_refuses_non_finite_coordinates_before_calling_it(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """pymeshlab crashes the process (SIGSEGV, exit -11) remeshing a grid with one vertex at inf;
    the call is refused first with one line. Run in a child so that a crash fails the test only."""
    import subprocess
    import sys

    code = (
        "import numpy as np, sys\n"
        "from nirspi_pipe.mesh.remesh import clean_and_remesh\n"
        "n = 9\n"
        "x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))\n"
        "v = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)]) * 1e-3\n"
        "i = np.arange(n * n).reshape(n, n)\n"
        "a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()\n"
        "f = np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])])\n"
        "v[40] = float(sys.argv[1])\n"
        "try:\n"
        "    clean_and_remesh(v, f, 1e-3, 3)\n"
        "except Exception as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    for value in ("inf", "-inf", "nan"):
        out = subprocess.run([sys.executable, "-c", code, value], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, (value, out.returncode, out.stderr[-500:])
        assert out.stdout.splitlines() == [
            "NirspiError mesh clean-up (pymeshlab): 1 vertices with non-finite coordinates; allowed: finite ones"
        ], out.stdout
