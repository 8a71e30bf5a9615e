"""Issue #4, "must show": at 25 % sampling, spiral / zigzag / cake_cutting with fista_tv beat
basic with fwht on PSNR, on the sphere and on the camera image (64², noise-free simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.metrics import psnr
from nirspi_pipe.patterns.orders import Basic, CakeCutting, Spiral, Zigzag
from nirspi_pipe.scene.objects import ImageTarget, Sphere
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera

N = 64
RATIO = 0.25
#: The margin each must clear, dB (measured: ≥ 31 dB on the sphere, ≥ 13 dB on the camera).
MARGIN_DB = 10.0


def _psnr(scene, order, solver) -> float:  # type: ignore[no-untyped-def]
    acq = Simulator().acquire(scene, order.select(N), N, np.random.default_rng(0))
    return psnr(scene.radiance, solver.solve(acq).data)


@pytest.fixture(scope="module", params=["sphere", "camera"])
def scene(request):  # type: ignore[no-untyped-def]
    model = Sphere() if request.param == "sphere" else ImageTarget(path="skimage:camera")
    return model.render(Camera(resolution=N))


@pytest.mark.parametrize("order", [Spiral(RATIO), Zigzag(RATIO), CakeCutting(RATIO)], ids=lambda o: type(o).__name__)
def test_quarter_sampling_fista_tv_beats_basic_fwht(scene, order):
    base = _psnr(scene, Basic(RATIO), FWHTSolver())
    ours = _psnr(scene, order, FistaTVSolver())
    print(
        f"{scene.name} {type(order).__name__}+fista_tv {ours:.2f} dB vs basic+fwht {base:.2f} dB: +{ours - base:.2f} dB"
    )
    assert ours > base + MARGIN_DB
