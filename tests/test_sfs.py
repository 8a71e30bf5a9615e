"""Shape from shading: sphere recovery, hard inputs, warnings and configs."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sfs.models import LaxFriedrichsSFS, OrenNayarSFS, PerspectiveSFS, PhongSFS, oren_nayar_ab
from nirspi_pipe.sfs.sweeping import BIG, SweepProblem, solve_numpy
from nirspi_pipe.types import Camera, Image2D

CAM = Camera(resolution=64)


@pytest.fixture(scope="module")
def sphere():
    """The paper's sphere at 64², its truth depth in pixel pitches at the nearest point."""
    scene = Sphere().render(CAM)
    m = scene.mask
    zmin = scene.depth_m[m].min()
    truth = (scene.depth_m - zmin) / (zmin / CAM.focal_px)
    cos = np.where(m, scene.radiance / 0.8, 0.0)  # reflectance 0.8
    return scene, truth, cos, m & (scene.radiance > 0.2 * 0.8)


def _rmse(depth, truth, ev):
    return float(np.sqrt(np.mean((depth.depth_m - truth)[ev] ** 2)))


@pytest.mark.parametrize("scheme,limit", [("godunov", 1.6), ("lax_friedrichs", 2.2)])
def test_orthographic_recovers_sphere(sphere, scheme, limit):
    scene, truth, _, ev = sphere
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = LaxFriedrichsSFS(scheme=scheme).solve(Image2D(scene.radiance), CAM)
    # depth range of the evaluated region is ~12 px: the error is ~10 % of it (first order)
    assert _rmse(d, truth, ev) < limit
    assert d.metric is False and d.info["converged"] and d.info["sweeps"] >= 4
    assert d.info["backend"] == "numpy" and d.info["final_change"] <= 1e-4
    assert abs(d.info["albedo"] - 0.8) < 0.01
    assert (d.mask == (scene.radiance > 0.05 * 0.8 * 0.9999)).mean() > 0.99
    # convex towards the camera: the centre is nearest
    assert d.depth_m[31:33, 31:33].max() < 0.1 < d.depth_m[32, 50]


def test_lax_friedrichs_close_to_godunov(sphere):
    scene, _, _, ev = sphere
    a = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(scene.radiance), CAM)
    b = LaxFriedrichsSFS(scheme="lax_friedrichs").solve(Image2D(scene.radiance), CAM)
    assert np.sqrt(np.mean((a.depth_m - b.depth_m)[ev] ** 2)) < 1.5


def test_godunov_equals_scikit_fmm_first_order():
    skfmm = pytest.importorskip("skfmm")
    from nirspi_pipe.benchmarks.sfs import sphere_problem

    f, fixed, z_true, mask, phi, z_src = sphere_problem(64)
    ours = solve_numpy(SweepProblem(f, fixed, np.where(fixed, z_true, BIG)), "godunov").z
    ref = np.abs(np.asarray(skfmm.travel_time(phi, 1.0 / f, order=1))) + z_src
    assert np.max(np.abs(ours - ref)[mask]) < 1e-6  # the same discrete solution


def _falloff_image(scene):
    x, y = CAM.pixel_coords(1)
    r = scene.depth_m * np.sqrt(1 + x[..., 0] ** 2 + y[..., 0] ** 2)
    rmin = r[scene.mask].min()
    return np.where(scene.mask, scene.radiance * (rmin / np.where(scene.mask, r, 1.0)) ** 2, 0.0)


def test_perspective_recovers_sphere(sphere):
    scene, truth, _, ev = sphere
    d = PerspectiveSFS(falloff=True).solve(Image2D(_falloff_image(scene)), CAM)
    assert d.info["converged"] and d.info["falloff"] is True
    assert _rmse(d, truth, ev) < 2.0
    d2 = PerspectiveSFS(falloff=False).solve(Image2D(scene.radiance), CAM)
    assert _rmse(d2, truth, ev) < 3.0
    # the fall-off image read without the fall-off model is badly wrong
    d3 = PerspectiveSFS(falloff=False).solve(Image2D(_falloff_image(scene)), CAM)
    assert _rmse(d3, truth, ev) > 1.5 * _rmse(d, truth, ev)


def test_oren_nayar_and_phong_recover_sphere(sphere):
    scene, truth, c, ev = sphere
    a, b = oren_nayar_ab(0.5)
    on = np.where(scene.mask, 0.7 * (a * c + b * (1 - c * c)), 0.0)
    d = OrenNayarSFS(roughness_rad=0.5, scheme="godunov").solve(Image2D(on), CAM)
    lam = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(on), CAM)
    assert _rmse(d, truth, ev) < 1.6 < _rmse(lam, truth, ev)
    ph = np.where(scene.mask, 0.9 * (0.6 * c + 0.4 * c**20), 0.0)
    d = PhongSFS(specular=0.4, shininess=20, scheme="godunov").solve(Image2D(ph), CAM)
    lam = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(ph), CAM)
    assert _rmse(d, truth, ev) < 1.6 < _rmse(lam, truth, ev)


def test_not_converged_warns(sphere):
    scene = sphere[0]
    with pytest.warns(UserWarning, match="not converged"):
        d = LaxFriedrichsSFS(max_sweeps=4).solve(Image2D(scene.radiance), CAM)
    assert d.info["converged"] is False and d.info["sweeps"] == 4 and d.info["final_change"] > 1e-4
    assert np.isfinite(d.depth_m).all()


@pytest.mark.parametrize("model", [LaxFriedrichsSFS(), LaxFriedrichsSFS(scheme="second_order"), PerspectiveSFS()])
def test_a_black_image_is_not_swept(model: object) -> None:
    """No object pixel: an empty depth map at once (the perspective model with fall-off swept the
    whole black 32² grid for 2 s; docs/hardcases.md, sfs-perspective-black)."""
    with pytest.warns(UserWarning, match="no object pixels"):
        d = model.solve(Image2D(np.zeros((32, 32))), Camera(resolution=32))  # type: ignore[attr-defined]
    assert not d.mask.any() and np.all(d.depth_m == 0.0) and d.info["sweeps"] == 0 and d.info["converged"]


def test_constant_image():
    img = Image2D(np.full((16, 16), 0.6))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = LaxFriedrichsSFS().solve(img, CAM)  # auto albedo: a plane facing the camera
    assert d.mask.all() and np.all(d.depth_m == 0.0)
    with pytest.warns(UserWarning, match="no Dirichlet data"):
        d = LaxFriedrichsSFS(albedo=0.8).solve(img, CAM)  # |∇z| = const > 0: no singular point
    assert np.isfinite(d.depth_m).all()


def test_brighter_than_albedo_and_dark_image():
    img = np.zeros((16, 16))
    img[4:12, 4:12] = 0.9
    with pytest.warns(UserWarning, match="brighter than the albedo"):
        d = LaxFriedrichsSFS(albedo=0.5).solve(Image2D(img), CAM)
    assert np.isfinite(d.depth_m).all() and d.mask.sum() == 64
    with pytest.warns(UserWarning, match="no object pixels"):
        d = LaxFriedrichsSFS().solve(Image2D(np.zeros((8, 8))), CAM)
    assert not d.mask.any() and np.all(d.depth_m == 0.0)
    with pytest.warns(UserWarning, match="non-finite"):
        bad = img.copy()
        bad[0, 0] = np.nan
        d = LaxFriedrichsSFS().solve(Image2D(bad), CAM)
    assert np.isfinite(d.depth_m).all()


def test_salt_noise_median(sphere):
    scene, truth, _, ev = sphere
    rng = np.random.default_rng(1)
    img = scene.radiance.copy()
    salt = rng.random(img.shape) < 0.01
    img[salt] = 1.0
    noisy = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(img), CAM)
    clean = LaxFriedrichsSFS(scheme="godunov", median_px=3).solve(Image2D(img), CAM)
    assert np.isfinite(noisy.depth_m).all()
    assert _rmse(clean, truth, ev) < 0.5 * _rmse(noisy, truth, ev)


@st.composite
def hard_images(draw):
    n = draw(st.sampled_from([2, 4, 8, 16, 32]))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    kind = draw(st.sampled_from(["smooth", "constant", "zeros", "saturated", "salt", "random"]))
    if kind == "constant":
        img = np.full((n, n), draw(st.floats(0.0, 2.0)))
    elif kind == "zeros":
        img = np.zeros((n, n))
    else:
        c = np.arange(n) + 0.5 - n / 2
        r2 = (c[None, :] ** 2 + c[:, None] ** 2) / max(1.0, (0.4 * n) ** 2)
        img = np.sqrt(np.clip(1 - r2, 0, 1))
        if kind == "saturated":
            img = np.minimum(3.0 * img, 1.5)
        elif kind == "salt":
            img[rng.random(img.shape) < 0.1] = 1.0
        elif kind == "random":
            img = rng.random((n, n)) * draw(st.floats(0.0, 5.0))
    holes = rng.random(img.shape) < draw(st.floats(0.0, 0.5))
    return np.where(holes, 0.0, img)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    img=hard_images(),
    scheme=st.sampled_from(["godunov", "lax_friedrichs"]),
    albedo=st.sampled_from(["auto", 0.5, 1.0]),
    persp=st.booleans(),
)
def test_hard_inputs_stay_finite(img, scheme, albedo, persp):
    if persp and min(img.shape) < 3:
        with pytest.raises(NirspiError, match="at least 3x3"):
            PerspectiveSFS().solve(Image2D(img), CAM)
        return
    if persp:
        stage = PerspectiveSFS(falloff=bool(img.sum() % 2 < 1), albedo=albedo, max_sweeps=200)
    else:
        stage = LaxFriedrichsSFS(scheme=scheme, albedo=albedo, max_sweeps=200)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = stage.solve(Image2D(img), CAM)
    assert d.depth_m.shape == img.shape and np.isfinite(d.depth_m).all()
    assert np.all(d.depth_m >= 0.0) and not np.any(d.mask & (img <= 0))
    assert np.all(d.depth_m[~d.mask] == 0.0)


def test_large_grid_512():
    n = 512
    c = np.arange(n) + 0.5 - n / 2
    r = np.hypot(c[None, :], c[:, None])
    img = np.sqrt(np.clip(1 - (r / (0.45 * n)) ** 2, 0, 1))
    img[::37, ::41] = 0.0  # dead pixels
    d = LaxFriedrichsSFS(scheme="godunov").solve(Image2D(img), Camera(resolution=512))
    assert np.isfinite(d.depth_m).all() and d.info["converged"]
    truth = 0.45 * n - np.sqrt(np.clip((0.45 * n) ** 2 - r**2, 0, None))
    ev = d.mask & (img > 0.2)
    assert np.sqrt(np.mean((d.depth_m - truth)[ev] ** 2)) < 0.02 * 0.45 * n


@pytest.mark.parametrize(
    "cls,kw,key",
    [
        (LaxFriedrichsSFS, {"scheme": "upwind"}, "scheme"),
        (LaxFriedrichsSFS, {"backend": "cuda"}, "backend"),
        (LaxFriedrichsSFS, {"tol": 0}, "tol"),
        (LaxFriedrichsSFS, {"max_sweeps": 2}, "max_sweeps"),
        (LaxFriedrichsSFS, {"albedo": 1.5}, "albedo"),
        (LaxFriedrichsSFS, {"albedo": "max"}, "albedo"),
        (LaxFriedrichsSFS, {"min_intensity": 0}, "min_intensity"),
        (LaxFriedrichsSFS, {"median_px": 2}, "median_px"),
        (PerspectiveSFS, {"scheme": "godunov"}, "scheme"),
        (OrenNayarSFS, {"roughness_rad": 0.9}, "roughness_rad"),
        (PhongSFS, {"specular": 1.0}, "specular"),
    ],
)
def test_config_errors(cls, kw, key):
    with pytest.raises(ConfigError) as err:
        cls(**kw)
    assert err.value.key == key


@pytest.mark.parametrize("option", ["lax_friedrichs", "godunov", "perspective", "oren_nayar", "phong"])
def test_configs_compose_and_instantiate(option):
    from hydra import compose, initialize_config_module

    from nirspi_pipe.pipeline import build

    with initialize_config_module(config_module="nirspi_pipe.conf", version_base=None):
        cfg = compose(config_name="config", overrides=[f"sfs={option}"])
    stage = build(cfg.sfs, "sfs")
    assert hasattr(stage, "solve")
    img = np.zeros((8, 8))
    img[2:6, 2:6] = [[0.5, 0.7, 0.7, 0.5], [0.7, 1.0, 1.0, 0.7], [0.7, 1.0, 1.0, 0.7], [0.5, 0.7, 0.7, 0.5]]
    d = stage.solve(Image2D(img), Camera(resolution=8))
    assert np.isfinite(d.depth_m).all() and d.mask.sum() == 16
