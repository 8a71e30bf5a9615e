"""Normalised image metrics (least-squares gain and offset to the camera's noise-free image) and
the simulator's reference image."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nirspi_pipe.metrics import PSNR_CAP_DB, ImageMetrics, fit_gain_offset, normalised_pair
from nirspi_pipe.physics.detector import IdealDetector, Photodiode
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.physics.fog import MeasuredFog
from nirspi_pipe.physics.light import Background
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.stages import Products
from nirspi_pipe.types import Camera


@settings(max_examples=40, deadline=None)
@given(a=st.floats(-1e3, 1e3).filter(lambda v: abs(v) > 1e-3), b=st.floats(-1e3, 1e3), seed=st.integers(0, 99))
def test_gain_offset_fit_inverts_an_affine_map(a, b, seed):
    ref = np.random.default_rng(seed).random((8, 8))
    gain, offset = fit_gain_offset(ref, a * ref + b)
    assert np.allclose(gain * (a * ref + b) + offset, ref, atol=1e-9 * max(1.0, abs(b)))


def test_constant_estimate_gets_the_mean():
    ref = np.arange(16.0).reshape(4, 4)
    assert fit_gain_offset(ref, np.ones((4, 4))) == (0.0, ref.mean())
    nref, nest = normalised_pair(ref, np.zeros((4, 4)))
    assert nref.max() == 1.0 and np.allclose(nest, nref.mean())


def _run(sim: Simulator, n: int = 32):
    scene = Sphere().render(Camera(n))
    acq = sim.acquire(scene, np.arange(n * n), n, np.random.default_rng(1))
    img = FWHTSolver().solve(acq)
    return ImageMetrics().compute(Products(scene, acq, img))


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(beta=st.floats(0.0, 30.0), klux=st.floats(0.0, 100.0), gain=st.sampled_from([0.0, 0.01, 1.0]))
def test_noise_free_run_scores_at_least_100_db_in_fog(beta, klux, gain):
    """Issue 11: a noise-free reconstruction reaches >= 100 dB whatever the fog and background
    (the raw radiometric PSNR does not: it keeps the clear-air gain)."""
    fog = MeasuredFog(beta_per_m=beta, backscatter_gain=gain) if beta > 0 else None
    m = _run(Simulator(forward_model(fog=fog, illumination=Background(klux=klux), detector=IdealDetector())))
    assert m["psnr"] >= 100.0 and m["psnr"] <= PSNR_CAP_DB
    assert m["ssim"] > 0.9999
    if beta > 5:
        assert m["psnr_raw"] < 40.0  # the radiometric score still sees the fog's loss


def test_reference_keeps_fall_off_and_fog_and_noise_lowers_the_score():
    fog = MeasuredFog(beta_per_m=1.15, backscatter_gain=0.01)
    sim = Simulator(forward_model(fog=fog, detector=Photodiode()))
    scene = Sphere().render(Camera(32))
    ref = sim.reference_image(scene)
    obj = scene.mask
    # the front of the sphere is nearer: brighter relative to its radiance (1/r^2) than its rim
    ratio = ref[obj] / np.maximum(scene.radiance[obj], 1e-12)
    assert ratio.max() > 1.1 * ratio.min()
    assert np.all(ref[~obj] > 0)  # the veil lights the background
    m = _run(sim)
    assert 5.0 < m["psnr"] < 100.0  # the photodiode's noise is scored


def test_fog_fills_only_the_chamber():
    """The fog attenuates min(range, extent) of each ray: an object beyond the chamber sees the
    same transmission as one at its far wall."""

    def peak_ratio(distance_mm: float) -> float:
        scene = Sphere(distance_mm=distance_mm).render(Camera(16))
        clear = Simulator(forward_model(detector=Photodiode())).reference_image(scene)
        fog = MeasuredFog(beta_per_m=2.0, extent_mm=350.0, backscatter_gain=0.0)
        foggy = Simulator(forward_model(fog=fog, detector=Photodiode())).reference_image(scene)
        return float(foggy[scene.mask].sum() / clear[scene.mask].sum())

    assert np.isclose(peak_ratio(600.0), peak_ratio(1000.0), rtol=1e-9)
    assert np.isclose(peak_ratio(600.0), np.exp(-2 * 2.0 * 0.35), rtol=1e-9)
    assert peak_ratio(200.0) > peak_ratio(600.0)
