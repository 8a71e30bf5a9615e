"""The paper's objects (torus, cube, U-shape), the flat board and mesh files."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.scene.shapes import (
    Cube,
    MeshScene,
    Plane,
    Torus,
    UShape,
    closed_orientation,
    load_mesh,
    raycast_mesh,
    rotation_matrix,
)
from nirspi_pipe.types import Camera


@pytest.fixture(scope="module")
def sphere_files(tmp_path_factory):
    import pyvista as pv

    d = tmp_path_factory.mktemp("meshes")
    mesh = pv.Sphere(radius=25.0, theta_resolution=60, phi_resolution=30)
    paths = {}
    for ext in ("ply", "stl", "obj"):
        paths[ext] = str(d / f"sphere.{ext}")
        mesh.save(paths[ext])
    return paths


def _common_checks(scene, n):
    assert scene.radiance.shape == (n, n)
    assert np.isfinite(scene.radiance).all() and scene.radiance.min() >= 0 and scene.radiance.max() <= 1
    assert scene.mask.any()
    assert np.isfinite(scene.depth_m[scene.mask]).all()
    assert np.isinf(scene.depth_m[scene.coverage == 0]).all()
    nrm = np.linalg.norm(scene.normals[scene.mask], axis=-1)
    assert np.allclose(nrm, 1.0)
    edge = (scene.coverage > 0) & (scene.coverage < 1)
    assert edge.any()  # anti-aliased edges


@pytest.mark.parametrize("model", [Torus(), Cube(), UShape(), Plane(size_mm=43.0, supersample=4)])
def test_builtin_objects_render(model):
    scene = model.render(Camera(32))
    _common_checks(scene, 32)
    assert scene.depth_m[scene.mask].min() > 0.15 and scene.depth_m[scene.mask].max() < 0.25


def test_torus_has_a_hole_and_the_right_size():
    n = 128
    scene = Torus(rotation_deg=[0, 0, 0]).render(Camera(n))
    c = n // 2
    assert scene.coverage[c - 1 : c + 1, c - 1 : c + 1].max() == 0.0  # the hole
    f = Camera(n).focal_px
    cols = np.nonzero(scene.coverage[c] > 0.5)[0]
    # outer Ø55 mm at the near face (z = 200 − 7.5 mm) projected to pixels
    assert cols.max() - cols.min() + 1 == pytest.approx(f * 0.055 / 0.2, rel=0.08)
    # the tube's crest faces the camera: its radiance there is the reflectance
    assert scene.radiance.max() == pytest.approx(0.8, abs=0.01)
    assert scene.depth_m[scene.mask].min() == pytest.approx(0.2 - 0.0075, abs=5e-4)


def test_cube_face_on_is_a_flat_square():
    n = 64
    scene = Cube(rotation_deg=[0, 0, 0]).render(Camera(n))
    front = scene.coverage == 1.0
    assert np.allclose(scene.depth_m[front], 0.18, atol=1e-9)
    area_px = scene.coverage.sum()
    side_px = Camera(n).focal_px * 0.04 / 0.18
    assert area_px == pytest.approx(side_px**2, rel=0.03)


def test_u_shape_is_open_at_the_top():
    n = 64
    scene = UShape(rotation_deg=[0, 0, 0]).render(Camera(n))
    rows, cols = np.nonzero(scene.mask)
    top, mid = rows.min() + 2, n // 2
    assert not scene.mask[top, mid]  # between the arms
    assert scene.mask[rows.max() - 2, mid]  # the bar
    front = scene.depth_m[scene.coverage == 1.0]
    assert front.min() == pytest.approx(0.2 - 0.0085)  # the front face, 17 mm deep U
    assert np.median(front) == pytest.approx(0.2 - 0.0085)
    assert front.max() <= 0.2 + 0.0085  # perspective shows the inner side walls


def test_plane_fills_the_view_at_its_distance():
    scene = Plane(distance_mm=300.0, reflectance=0.4).render(Camera(16))
    assert scene.mask.all() and np.allclose(scene.depth_m, 0.3)
    assert scene.radiance.max() <= 0.4 and scene.radiance.min() > 0.4 * 0.95


@pytest.mark.parametrize("ext", ["ply", "stl", "obj"])
def test_mesh_files_render_like_the_analytic_sphere(sphere_files, ext):
    n = 64
    mesh = MeshScene(path=sphere_files[ext], size_mm=50.0, supersample=2).render(Camera(n))
    exact = Sphere(supersample=2).render(Camera(n))
    _common_checks(mesh, n)
    assert np.abs(mesh.coverage - exact.coverage).mean() < 0.01
    assert np.abs(mesh.radiance - exact.radiance).max() < 0.05
    both = mesh.mask & exact.mask
    assert np.abs(mesh.depth_m[both] - exact.depth_m[both]).max() < 2e-3  # facets of a 3600-triangle sphere


def test_back_face_culling_changes_nothing(sphere_files):
    cam = Camera(32)
    verts, faces = load_mesh(sphere_files["ply"])
    assert closed_orientation(faces, verts) == 1
    assert closed_orientation(faces[:, ::-1], verts) == -1
    assert closed_orientation(faces[:-3], verts) == 0
    vm = MeshScene(path=sphere_files["ply"]).placed_vertices(verts)
    a = raycast_mesh(cam, 2, vm, faces, orientation=0)
    b = raycast_mesh(cam, 2, vm, faces, orientation=1)
    assert np.array_equal(np.isfinite(a[1]), np.isfinite(b[1]))
    fin = np.isfinite(a[1])
    assert np.allclose(a[1][fin], b[1][fin])


def _brute_force(rays, v, f):
    """Möller–Trumbore of every ray against every triangle."""
    d = rays.reshape(-1, 3)
    t_best = np.full(d.shape[0], np.inf)
    for tri in f:
        p0, p1, p2 = v[tri]
        e1, e2 = p1 - p0, p2 - p0
        pv = np.cross(d, e2)
        det = pv @ e1
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        tv = -p0
        u = (pv @ tv) * inv
        q = np.cross(tv, e1)
        vv = (d @ q) * inv
        t = (e2 @ q) * inv
        hit = ok & (u >= 0) & (vv >= 0) & (u + vv <= 1) & (t > 1e-9)
        t_best = np.where(hit & (t < t_best), t, t_best)
    return t_best.reshape(rays.shape[:-1])


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), ntri=st.integers(1, 25))
def test_binned_raycast_equals_brute_force(seed, ntri):
    rng = np.random.default_rng(seed)
    cam = Camera(16)
    v = rng.uniform([-0.04, -0.04, 0.15], [0.04, 0.04, 0.25], size=(3 * ntri, 3))
    f = np.arange(3 * ntri).reshape(ntri, 3)
    rays, t, tri, u, w = raycast_mesh(cam, 2, v, f, chunk=64)
    want = _brute_force(rays, v, f)
    assert np.array_equal(np.isfinite(t), np.isfinite(want))
    assert np.allclose(t[np.isfinite(t)], want[np.isfinite(want)])


def test_rotation_matrix_is_orthonormal():
    r = rotation_matrix([10.0, 20.0, 30.0])
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("make", "key"),
    [
        (lambda: Torus(inner_diameter_mm=60.0), "inner_diameter_mm"),
        (lambda: Torus(reflectance=1.2), "reflectance"),
        (lambda: Cube(side_mm=-1.0), "side_mm"),
        (lambda: Cube(rotation_deg=[0, 0]), "rotation_deg"),
        (lambda: UShape(thickness_mm=50.0), "thickness_mm"),
        (lambda: Plane(distance_mm=-1.0), "distance_mm"),
        (lambda: MeshScene(path=""), "path"),
        (lambda: MeshScene(path="x.ply", size_mm=0.0), "size_mm"),
        (lambda: MeshScene(path="/nonexistent.ply").render(Camera(8)), "path"),
    ],
)
def test_impossible_scene_inputs_name_the_key(make, key):
    with pytest.raises(ConfigError) as err:
        make()
    assert err.value.key == key


@pytest.mark.parametrize(
    ("make", "key", "value"),
    [
        (lambda: Torus(distance_mm=1e-3), "distance_mm", 1e-3),  # the torus's 55 mm was never set
        (lambda: Sphere(distance_mm=20.0), "distance_mm", 20.0),
        (lambda: Cube(distance_mm=10.0), "distance_mm", 10.0),
        (lambda: Sphere(diameter_mm=500.0), "diameter_mm", 500.0),
        (lambda: Cube(side_mm=300.0), "side_mm", 300.0),  # its own value, not the diagonal 519.6
        (lambda: Torus(outer_diameter_mm=500.0, distance_mm=100.0), "outer_diameter_mm", 500.0),
    ],
)
def test_a_size_too_large_for_the_distance_names_the_key_that_was_changed(make, key, value):
    """Issue 40: never blame a key the user did not set. A size at its default with a changed
    distance names the distance; a changed size names the size, with the value the user gave."""
    with pytest.raises(ConfigError) as err:
        make()
    assert err.value.key == key and err.value.value == value
    assert str(err.value).startswith(f"{key}=") and "in front of the camera" in str(err.value)


def test_unreadable_mesh_file_names_the_key(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    with pytest.raises(ConfigError) as err:
        MeshScene(path=str(bad)).render(Camera(8))
    assert err.value.key == "path"


def test_every_new_config_option_composes_and_instantiates(sphere_files):
    from hydra import compose, initialize_config_module

    from nirspi_pipe.pipeline import build, run_pipeline

    groups = {
        "fog": ["none", "chamber", "measured"],
        "illumination": ["none", "klux"],
        "detector": ["ideal", "ingaas"],
        "scene": ["torus", "cube", "u_shape", "plane", "mesh"],
    }
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        for group, options in groups.items():
            for opt in options:
                extra = [f"scene.path={sphere_files['ply']}"] if opt == "mesh" else []
                cfg = compose("config", overrides=[f"{group}={opt}", "camera.resolution=8", *extra])
                assert build(cfg[group], group) is not None
                out = run_pipeline(cfg)
                assert np.isfinite(out.products.image.data).all()
