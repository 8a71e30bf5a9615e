"""Surface ``view`` (nirspi_pipe.mesh.viewmesh): the cloud triangulated as the camera sees it keeps
every point, joins no two surfaces across a depth jump or a hole, faces the camera, and refuses
clouds that admit no triangle in one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.mesh.metrics3d import Metrics3D
from nirspi_pipe.mesh.pointcloud import back_project
from nirspi_pipe.mesh.truthsurface import MAX_SLOPE
from nirspi_pipe.mesh.viewmesh import ViewTriangulation, view_faces
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Camera, PointCloud
from test_metrics3d_truth import _exact_products


def _cloud(depth: np.ndarray, mask: np.ndarray, cam: Camera) -> np.ndarray:
    return back_project(np.where(mask, depth, 0.0), cam)[mask]


def _edges_obey_jump_rule(verts: np.ndarray, faces: np.ndarray) -> bool:
    uv = verts[:, :2] / verts[:, 2:3]
    z = verts[:, 2]
    for a, b in ((0, 1), (1, 2), (0, 2)):
        i, j = faces[:, a], faces[:, b]
        d = np.linalg.norm(uv[i] - uv[j], axis=1)
        if not np.all(np.abs(z[i] - z[j]) <= MAX_SLOPE * np.minimum(z[i], z[j]) * d * (1 + 1e-12)):
            return False
    return True


def test_exact_sphere_keeps_every_point_and_scores_near_the_floor() -> None:
    cam = Camera(32)
    exact = _exact_products(Sphere(), cam)  # the exact surface point-sampled at the pixel centres
    pts = exact.cloud.points_m
    mesh = ViewTriangulation().reconstruct(PointCloud(points_m=pts))
    # nothing lost: every point but the few limb points that join no face is a vertex
    assert set(map(tuple, np.round(mesh.vertices_m, 12))) <= set(map(tuple, np.round(pts, 12)))
    assert len(mesh.vertices_m) >= 0.99 * len(pts)
    assert mesh.info["cloud_covered_fraction"] >= 0.99
    m = Metrics3D(scene=Sphere()).compute(dataclasses.replace(exact, mesh=mesh))
    floor = Metrics3D(scene=Sphere()).compute(exact)["chamfer_mm"]  # the grid mesh of the same points
    assert m["chamfer_mm"] < 1.5 * floor, (m["chamfer_mm"], floor)


@settings(max_examples=30, deadline=None)
@given(
    depths=st.lists(st.floats(0.15, 0.6), min_size=4, max_size=4),
    n=st.sampled_from([16, 32]),
)
def test_no_face_crosses_a_depth_jump(depths: list[float], n: int) -> None:
    cam = Camera(n)
    depth = np.empty((n, n))
    h = n // 2
    depth[:h, :h], depth[:h, h:], depth[h:, :h], depth[h:, h:] = depths
    pts = _cloud(depth, np.ones((n, n), dtype=bool), cam)
    verts, faces, info = view_faces(pts, 2.5)
    assert _edges_obey_jump_rule(verts, faces)
    assert info["points"] == info["vertices"] == n * n
    # a block at one depth is one surface: its 2·(h−1)² grid triangles are all there (and faces
    # between blocks only where the rule calls the step a slope)
    assert len(faces) >= 4 * 2 * (h - 1) ** 2


def test_no_face_spans_a_hole() -> None:
    cam = Camera(32)
    x, y = cam.pixel_coords()
    r = np.hypot(x[..., 0], y[..., 0])
    ring = (r > 0.6 * r.max() / 2) & (r < 0.9 * r.max() / 2)
    pts = _cloud(np.full((32, 32), 0.2), ring, cam)
    verts, faces, _ = view_faces(pts, 2.5)
    centre = verts[faces].mean(axis=1)
    rc = np.hypot(centre[:, 0] / centre[:, 2], centre[:, 1] / centre[:, 2])
    assert len(faces) > 0 and rc.min() > 0.55 * r.max() / 2  # nothing across the ring's inside


def test_faces_face_the_camera_and_input_order_does_not_matter() -> None:
    cam = Camera(32)
    scene = Sphere().render(cam)
    pts = _cloud(scene.depth_m, scene.mask, cam)
    verts, faces, _ = view_faces(pts, 2.5)
    normal = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normal, verts[faces].mean(axis=1)) < 0)
    perm = np.random.default_rng(1).permutation(len(pts))
    v2, f2, _ = view_faces(pts[perm], 2.5)

    def tris(v: np.ndarray, f: np.ndarray) -> set:
        return {tuple(sorted(map(tuple, np.round(v[t], 12)))) for t in f}

    assert tris(verts, faces) == tris(v2, f2)


def test_points_behind_the_camera_or_not_finite_are_left_out_and_duplicates_merged() -> None:
    base = np.array([[0.0, 0.0, 0.2], [0.01, 0.0, 0.2], [0.0, 0.01, 0.2], [0.01, 0.01, 0.2]])
    bad = np.array([[0.0, 0.0, -0.2], [np.nan, 0.0, 0.2], [0.0, np.inf, 0.2], [0.0, 0.0, 0.3]])
    verts, faces, info = view_faces(np.vstack([base, bad]), 2.5)
    assert info["points"] == 4 and len(faces) == 2
    assert np.allclose(np.sort(verts[:, 2]), 0.2)  # the farther point on the first ray was merged into the nearer


@pytest.mark.parametrize(
    "points, says",
    [
        (np.zeros((0, 3)), "at least 3 points"),
        (np.array([[0.0, 0.0, 0.2], [0.0, 0.0, 0.4], [0.0, 0.0, 0.6]]), "at least 3 points"),  # one ray
        (np.array([[0.0, 0.0, 0.2], [0.01, 0.0, 0.2], [0.02, 0.0, 0.2], [0.03, 0.0, 0.2]]), "admit no triangle"),
        (np.full((5, 3), np.nan), "at least 3 points"),
        (np.zeros((4, 2)), "shape (n, 3)"),
    ],
)
def test_clouds_without_a_triangle_are_refused_in_one_line(points: np.ndarray, says: str) -> None:
    with pytest.raises(NirspiError) as exc:
        ViewTriangulation().reconstruct(PointCloud(points_m=points))
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_every_triangle_dropped_is_one_line_naming_the_key() -> None:
    # two points near, one far away in depth: the only triangle crosses a jump
    pts = np.array([[0.0, 0.0, 0.2], [0.001, 0.0, 0.2], [0.0, 0.001, 0.9]])
    with pytest.raises(NirspiError, match="surface.max_edge_factor"):
        ViewTriangulation().reconstruct(PointCloud(points_m=pts))


def test_bad_edge_factor_names_the_key() -> None:
    with pytest.raises(ConfigError, match="max_edge_factor"):
        ViewTriangulation(max_edge_factor=0.5)


def test_remeshing_keeps_the_surface() -> None:
    cam = Camera(32)
    pts = _exact_products(Sphere(), cam).cloud.points_m
    mesh = ViewTriangulation(remesh_iterations=2).reconstruct(PointCloud(points_m=pts))
    assert len(mesh.faces) > 0 and mesh.info["remesher"] in ("compiled", "pymeshlab")
    r = np.linalg.norm(mesh.vertices_m - [0.0, 0.0, 0.2], axis=1)  # the default sphere: Ø50 mm at 200 mm
    assert np.all(np.abs(r - 0.025) < 0.002)
