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
    """Issue 33: ``auto`` is what was measured faster on the device, numpy on PoCL's CPU device
    (the device OMP is slower there) and wherever nothing was measured."""
    from nirspi_pipe.opencl_devices import choose, is_gpu
    from nirspi_pipe.solvers.omp_opencl import gpu_available, opencl_context

    assert OMPSolver(backend="numpy").effective_backend() == "numpy"
    if not ocl.opencl_available():
        assert OMPSolver().effective_backend() == "numpy"
        return
    dev = opencl_context()[0].devices[0]
    for size in (8, 64, 128):
        assert OMPSolver().effective_backend(size) == choose("omp", dev, size)[0]
    if not gpu_available() and not is_gpu(dev):
        assert OMPSolver().effective_backend(128) == "numpy"


def test_auto_follows_the_measured_table(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A row of the user's table (``nirspi-bench gpu --write-table``) decides ``auto`` for that
    device, stage and size; the nearest measured size at or below is used."""
    from nirspi_pipe import opencl_devices

    class Dev:
        name = "Some Device"

    monkeypatch.setenv("NIRSPI_DEVICE_TABLE", str(tmp_path / "t.json"))
    opencl_devices.load_table.cache_clear()
    try:
        assert opencl_devices.choose("omp", Dev(), 64)[0] == opencl_devices.DEFAULT_CHOICE["omp"]
        opencl_devices.write_table({"Some Device": {"omp": {32: "numpy", 128: "opencl"}, "sfs": {64: "numpy"}}})
        assert opencl_devices.choose("omp", Dev(), 64)[0] == "numpy"
        assert opencl_devices.choose("omp", Dev(), 128)[0] == "opencl"
        assert opencl_devices.choose("omp", Dev(), 512)[0] == "opencl"
        assert opencl_devices.choose("omp", Dev(), 8)[0] == "numpy"  # below every row: the smallest one's
        assert opencl_devices.choose("sfs", Dev(), 256) == ("numpy", "measured on Some Device at 64²")
        (tmp_path / "t.json").write_text("{not json")
        opencl_devices.load_table.cache_clear()
        assert (
            opencl_devices.choose("sfs", Dev(), 256)[0] == opencl_devices.DEFAULT_CHOICE["sfs"]
        )  # a broken file is ignored
    finally:
        monkeypatch.delenv("NIRSPI_DEVICE_TABLE")
        opencl_devices.load_table.cache_clear()


@pytest.mark.parametrize("bad", ["GPU", "1", "0:x", "", 3, "cuda"])
def test_device_spec_is_checked_in_one_line(bad) -> None:  # type: ignore[no-untyped-def]
    from nirspi_pipe.errors import ConfigError

    with pytest.raises(ConfigError, match="device=.*allowed: auto, cpu, gpu"):
        OMPSolver(device=bad)
    with pytest.raises(ConfigError, match="device=.*allowed: auto, cpu, gpu"):
        LaxFriedrichsSFS(device=bad)


def test_pyopencl_ctx_names_the_device_and_a_missing_one_fails_in_one_line(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from nirspi_pipe import opencl_devices
    from nirspi_pipe.errors import NirspiError

    if not ocl.opencl_available():
        pytest.skip("no OpenCL device here")
    import pyopencl as cl

    last = len(cl.get_platforms()) - 1
    opencl_devices.opencl_device.cache_clear()
    try:
        monkeypatch.setenv("PYOPENCL_CTX", f"{last}:0")
        assert opencl_devices.opencl_device("auto") == cl.get_platforms()[last].get_devices()[0]
        assert opencl_devices.opencl_device(f"{last}:0") == cl.get_platforms()[last].get_devices()[0]
        monkeypatch.setenv("PYOPENCL_CTX", "99:0")
        opencl_devices.opencl_device.cache_clear()  # read once per process
        with pytest.raises(NirspiError, match="PYOPENCL_CTX='99:0': no such OpenCL device"):
            opencl_devices.opencl_device("auto")
        with pytest.raises(NirspiError, match="no such OpenCL device"):
            opencl_devices.opencl_device("7:3")
    finally:
        opencl_devices.opencl_device.cache_clear()


def test_record_names_backend_and_device(sphere_image) -> None:  # type: ignore[no-untyped-def]
    image, cam = sphere_image
    out = LaxFriedrichsSFS(scheme="godunov", backend="numpy").solve(image, cam)
    assert out.info["device"] == "cpu (numpy)" and out.info["device_requested"] == "auto"
    if ocl.opencl_available():
        out = LaxFriedrichsSFS(scheme="godunov", backend="opencl", device="auto").solve(image, cam)
        assert out.info["backend"] == "opencl" and " / " in out.info["device"]
