"""Surfaces: power crust (Amenta et al. 2001, both labellings) and screened Poisson."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.mesh.powercrust import PowerCrust, compute_poles, power_crust
from nirspi_pipe.types import PointCloud

CENTRE, R = np.array([0.0, 0.0, 0.2]), 0.025


def fibonacci_sphere(n: int, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    u = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])
    r = R + np.random.default_rng(seed).normal(0, noise, n)
    return CENTRE + u * r[:, None]


def edge_counts(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_poles_of_sphere_samples():
    s = fibonacci_sphere(200)
    poles, radii, owner = compute_poles(s)
    inner = np.linalg.norm(poles - CENTRE, axis=1) < 0.5 * R
    # every sample has one pole at the centre (the medial axis of a sphere) and one outside
    assert np.bincount(owner[inner], minlength=200).tolist() == [1] * 200
    assert np.allclose(radii[inner], R, rtol=1e-6)


@pytest.mark.parametrize("noise", [0.0, 1e-4])
def test_power_crust_of_sphere_is_close_and_closed(noise):
    s = fibonacci_sphere(300, noise)
    v, f, info = power_crust(s, "amenta")
    d = np.abs(np.linalg.norm(v - CENTRE, axis=1) - R)
    assert d.max() < 1.5e-3 and d.mean() < 0.3e-3  # sample spacing is ~2.6 mm
    counts = edge_counts(f)
    assert np.mean(counts == 2) > 0.99  # (nearly) watertight
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.mean(np.einsum("ij,ij->i", n, v[f].mean(axis=1) - CENTRE) > 0) > 0.99  # outwards
    # covers the whole sphere: every sample is near the crust's surface
    from scipy.spatial import cKDTree

    from nirspi_pipe.mesh.metrics3d import sample_surface

    surf = sample_surface(v, f, 2e-4, np.random.default_rng(0))
    assert cKDTree(surf).query(s)[0].max() < 1e-3


def test_view_labelling_on_a_visible_cap():
    s = fibonacci_sphere(800)
    cap = s[s[:, 2] < CENTRE[2] - 0.005]  # the part a camera at the origin sees
    mesh = PowerCrust().reconstruct(PointCloud(cap))
    d = np.abs(np.linalg.norm(mesh.vertices_m - CENTRE, axis=1) - R)
    # sample spacing ~1.8 mm; the sheet is on the sphere, only its rim bends away a little
    assert len(mesh.faces) > len(cap)
    assert np.median(d) < 0.2e-3 and np.percentile(d, 95) < 1e-3 and d.max() < 3e-3
    closed = PowerCrust(closed=True).reconstruct(PointCloud(cap))
    assert len(closed.faces) >= len(mesh.faces)


def test_too_few_points_and_bad_config():
    with pytest.raises(NirspiError, match="at least 5"):
        PowerCrust().reconstruct(PointCloud(np.zeros((3, 3))))
    with pytest.raises(NirspiError, match="non-finite"):
        PowerCrust().reconstruct(PointCloud(np.full((10, 3), np.nan)))
    with pytest.raises(ConfigError, match="labelling"):
        PowerCrust(labelling="nope")


def test_coplanar_points_do_not_crash():
    g = np.stack(np.meshgrid(np.arange(8), np.arange(8)), -1).reshape(-1, 2) * 0.005
    plane = np.column_stack([g, np.full(len(g), 0.2)])
    try:
        mesh = PowerCrust().reconstruct(PointCloud(plane))
    except NirspiError:
        return  # a clear error is acceptable for a flat sheet of exactly coplanar points
    assert np.all(np.isfinite(mesh.vertices_m))


def test_poisson_on_a_cap():
    from nirspi_pipe.mesh.poisson import ScreenedPoisson

    s = fibonacci_sphere(600)
    cap = s[s[:, 2] < CENTRE[2] - 0.005]
    normals = (cap - CENTRE) / R
    mesh = ScreenedPoisson().reconstruct(PointCloud(cap, normals=normals))
    d = np.abs(np.linalg.norm(mesh.vertices_m - CENTRE, axis=1) - R)
    assert (
        len(mesh.faces) > 100 and np.median(d) < 0.2e-3 and np.percentile(d, 90) < 1.5e-3 and d.max() < 4e-3
    )  # rim extrapolates
    # without normals pymeshlab estimates them, oriented towards the camera
    mesh2 = ScreenedPoisson().reconstruct(PointCloud(cap))
    assert len(mesh2.faces) > 100
    with pytest.raises(ConfigError, match="depth"):
        ScreenedPoisson(depth=2)


@pytest.mark.parametrize(
    "stage", ["nirspi_pipe.mesh.powercrust:PowerCrust", "nirspi_pipe.mesh.poisson:ScreenedPoisson"]
)
@pytest.mark.parametrize("remesher", ["auto", "pymeshlab"])
def test_surface_stages_load_and_compile_when_built_not_when_timed(stage: str, remesher: str) -> None:
    """Everything the timed surface stage runs is imported (pymeshlab: ~0.3 s) or compiled (numba:
    seconds when its cache is cold) when the stage is built, before the runner's timer: the first
    mesh of a process (every sweep job) imports no module and compiles no kernel."""
    import subprocess
    import sys

    module, name = stage.split(":")
    code = (
        "import sys, importlib, numpy as np\n"
        "from nirspi_pipe.types import PointCloud\n"
        f"cls = getattr(importlib.import_module({module!r}), {name!r})\n"
        "assert 'pymeshlab' not in sys.modules, 'imported with the module'\n"
        f"stage = cls(remesher={remesher!r})\n"
        "from nirspi_pipe.mesh.jitcache import KERNEL_MODULES\n"
        "mods = [importlib.import_module('nirspi_pipe.mesh.' + k) for k in KERNEL_MODULES]\n"
        "kernels = [getattr(m, k) for m in mods for k in dir(m) if hasattr(getattr(m, k), 'signatures')]\n"
        "before = {id(k): len(k.signatures) for k in kernels}\n"
        "mods = set(sys.modules)\n"
        "u, v = np.meshgrid(np.linspace(-0.5, 0.5, 12), np.linspace(-0.5, 0.5, 12))\n"
        "pts = np.column_stack([u.ravel(), v.ravel(), 2.0 - np.sqrt(1.0 - u.ravel()**2 - v.ravel()**2)]) * 0.05\n"
        "mesh = stage.reconstruct(PointCloud(pts + np.random.default_rng(0).normal(0, 1e-5, pts.shape)))\n"
        "assert len(mesh.faces) > 0\n"
        "new = sorted(set(sys.modules) - mods)\n"
        "assert not new, f'imported while timed: {new}'\n"
        "grew = [k.__name__ for k in kernels if len(k.signatures) != before[id(k)]]\n"
        "assert not grew, f'compiled while timed: {grew}'\n"
        "print(mesh.info['remesher'])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, timeout=300, capture_output=True, text=True)
    assert out.stdout.strip() == ("compiled" if remesher == "auto" else "pymeshlab")


def test_power_crust_is_bit_identical_across_openblas_kernel_sets() -> None:
    """Issue 12: the pole computation uses no BLAS/LAPACK (Cramer's rule written out) and the
    samples are snapped to CLOUD_QUANTUM_M, so the mesh is the same bits under every kernel set
    OpenBLAS can run here (with LAPACK's solve, Sandybridge gave 782 vertices where Haswell gave 783)."""
    import os
    import subprocess
    import sys

    code = (
        "import hashlib, numpy as np\n"
        "from nirspi_pipe.mesh.powercrust import PowerCrust\n"
        "from nirspi_pipe.types import PointCloud\n"
        "i = np.arange(400) + 0.5\n"
        "phi, th = np.arccos(1 - 2 * i / 400), np.pi * (1 + 5**0.5) * i\n"
        "u = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])\n"
        "r = 0.025 + np.random.default_rng(3).normal(0, 2e-4, 400)\n"
        "pts = np.array([0.0, 0.0, 0.2]) + u * r[:, None]\n"
        "pts = pts[pts[:, 2] < 0.2 + 0.01]\n"  # the camera-facing part, as SFS + iToF sees it
        "m = PowerCrust().reconstruct(PointCloud(points_m=pts))\n"
        "print(hashlib.sha256(m.vertices_m.tobytes() + m.faces.tobytes()).hexdigest())\n"
    )
    digests = {}
    for core in ("", "Haswell", "Sandybridge", "Prescott"):
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        if core:
            env["OPENBLAS_CORETYPE"] = core
        run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        if run.returncode < 0 or run.returncode == 132:  # this CPU cannot execute that kernel set
            continue
        assert run.returncode == 0, run.stderr[-2000:]
        digests[core or "detected"] = run.stdout.strip()
    assert len(digests) >= 2 and len(set(digests.values())) == 1, digests


def test_cloud_coverage_counts_the_points_the_mesh_lies_near():
    """Issue 44: the crust says when it loses most of a shape. The coverage of a cloud by a
    mesh is 1 for the cap's own crust, the kept share plus a band along the cut when half the
    faces are dropped from one side, and 0 for a mesh far from the cloud."""
    from nirspi_pipe.mesh.powercrust import cloud_coverage
    from nirspi_pipe.mesh.remesh import sample_spacing

    s = fibonacci_sphere(800)
    cap = s[s[:, 2] < CENTRE[2] - 0.005]
    mesh = PowerCrust().reconstruct(PointCloud(cap))
    assert mesh.info["cloud_covered_fraction"] == 1.0
    spacing = sample_spacing(cap)
    v, f = mesh.vertices_m, mesh.faces
    left = f[v[f].mean(axis=1)[:, 0] < CENTRE[0]]  # the faces on one side of the cap
    half = cloud_coverage(v, left, cap, spacing)
    share = float(np.mean(cap[:, 0] < CENTRE[0]))
    # a band of about two spacings plus half an edge beyond the cut still counts as covered
    assert share <= half < 0.8
    assert cloud_coverage(v + np.array([0.0, 0.0, 1.0]), f, cap, spacing) == 0.0


def test_a_crust_that_loses_most_of_the_cloud_warns(monkeypatch):
    import nirspi_pipe.mesh.powercrust as pc

    s = fibonacci_sphere(800)
    cap = s[s[:, 2] < CENTRE[2] - 0.005]
    monkeypatch.setattr(pc, "cloud_coverage", lambda *a: 0.3)
    with pytest.warns(UserWarning, match="lost most of the shape"):
        mesh = PowerCrust().reconstruct(PointCloud(cap))
    assert mesh.info["cloud_covered_fraction"] == 0.3
