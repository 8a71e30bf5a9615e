"""Issue #15: ``backend: auto`` — OpenCL where a device builds the kernel, numpy otherwise, the
record says which, and kernels are built when the stage is constructed (never inside a solve)."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sfs import opencl as ocl
from nirspi_pipe.sfs.models import LaxFriedrichsSFS, PerspectiveSFS
from nirspi_pipe.solvers.omp import OMPSolver
from nirspi_pipe.types import Camera, Image2D


@pytest.fixture(scope="module")
def sphere_image() -> tuple[Image2D, Camera]:
    cam = Camera(resolution=32)
    return Image2D(Sphere().render(cam).radiance), cam


@pytest.mark.parametrize("scheme", ["lax_friedrichs", "godunov", "second_order"])
def test_sfs_auto_uses_opencl_where_it_builds_and_says_so(sphere_image, scheme) -> None:  # type: ignore[no-untyped-def]
    image, cam = sphere_image
    auto = LaxFriedrichsSFS(scheme=scheme, backend="auto")
    expected = "opencl" if ocl.warm_up(0, scheme) else "numpy"
    assert auto.effective_backend() == expected
    out = auto.solve(image, cam)
    assert out.info["backend"] == expected and out.info["backend_requested"] == "auto"
    ref = LaxFriedrichsSFS(scheme=scheme, backend="numpy").solve(image, cam)
    assert ref.info["backend"] == "numpy"
    np.testing.assert_allclose(out.depth_m, ref.depth_m, atol=1e-3)  # the same solution (tol 1e-4 px)


def test_sfs_kernel_is_built_at_construction(sphere_image) -> None:  # type: ignore[no-untyped-def]
    if not ocl.warm_up(1, "lax_friedrichs"):
        pytest.skip("no OpenCL device builds the kernel here")
    ocl._program.cache_clear()
    PerspectiveSFS(backend="auto", falloff=False)  # model 1
    built = ocl._program.cache_info().currsize
    assert built == 1
    image, cam = sphere_image
    PerspectiveSFS(backend="auto", falloff=False).solve(image, cam)
    assert ocl._program.cache_info().misses == 1  # the solve reused the kernel built before it


def test_omp_auto_is_numpy_on_cpu_devices() -> None:
    from nirspi_pipe.solvers.omp_opencl import gpu_available

    assert OMPSolver().effective_backend() == ("opencl" if gpu_available() else "numpy")
    assert OMPSolver(backend="numpy").effective_backend() == "numpy"
