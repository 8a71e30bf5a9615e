"""The OpenCL back end of the SFS sweeping: its kernel source compiled as C for one work-item
(skipped without a C compiler), which checks the kernel's arithmetic and sweep logic against numpy
on any machine; its one-line error; no compilation inside a timed solve. The real OpenCL path
against numpy is in the parity harness (tests/test_parity.py, family ``sfs``), skipped when no
device here builds float64 kernels (PoCL fails with ``unknown target CPU 'generic'`` on CPUs its
LLVM does not know).
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess

import numpy as np
import pytest

from nirspi_pipe.backends.sfs import sfs_first_order_problems
from nirspi_pipe.sfs import opencl as ocl
from nirspi_pipe.sfs.sweeping import BIG, SweepProblem, SweepResult, solve_numpy

#: numpy and OpenCL do the same operations in the same order (FP_CONTRACT off); only exp() of
#: the fall-off model may differ in the last bits.
ATOL_PX = 1e-9


def _agree(a: SweepResult, b: SweepResult) -> None:
    assert a.sweeps == b.sweeps and a.converged == b.converged
    assert np.max(np.abs(a.z - b.z)) <= ATOL_PX
    assert abs(a.final_change - b.final_change) <= ATOL_PX


_SHIM = r"""
#include <math.h>
#define __kernel
#define __global
#define __local
typedef unsigned char uchar;
#define get_local_id(x) 0
#define get_local_size(x) 1
#define barrier(x)
static int max(int a, int b) { return a > b ? a : b; }
static int min(int a, int b) { return a < b ? a : b; }
#define inline static inline
"""


def _solve_c(lib, problem: SweepProblem, scheme: str, tol=1e-4, max_sweeps=2000) -> SweepResult:
    rows, cols = problem.rhs.shape
    upd = ~problem.fixed
    if scheme == "lax_friedrichs":
        upd = upd.copy()
        upd[0, :] = upd[-1, :] = upd[:, 0] = upd[:, -1] = False
    z = np.ascontiguousarray(problem.init, np.float64).copy()
    arrays = [
        np.ascontiguousarray(problem.rhs, np.float64),
        np.ascontiguousarray(upd, np.uint8),
        np.ascontiguousarray(problem.fixed, np.uint8),
        np.ascontiguousarray(problem.xhat if problem.xhat is not None else np.zeros(cols)),
        np.ascontiguousarray(problem.yhat if problem.yhat is not None else np.zeros(rows)),
    ]
    out, red = np.zeros(3), np.zeros(1)
    sx, sy = problem.sigmas()
    p = ctypes.c_void_p
    fn = lib.fsm
    fn.restype = None
    fn.argtypes = [p] * 6 + [ctypes.c_int, ctypes.c_int] + [ctypes.c_double] * 3 + [ctypes.c_int, ctypes.c_double, p, p]
    fn(
        z.ctypes.data,
        *(a.ctypes.data for a in arrays),
        rows,
        cols,
        sx,
        sy,
        2.0 / problem.focal_px,
        max(1, -(-max_sweeps // 4)),
        tol,
        out.ctypes.data,
        red.ctypes.data,
    )
    return SweepResult(z, int(out[0]), float(out[1]), bool(out[2]))


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_kernel_source_as_c_agrees_with_numpy(tmp_path):
    for _name, problem, scheme in sfs_first_order_problems():
        tag = f"{problem.model}{int(scheme == 'godunov')}"
        src = tmp_path / f"k{tag}.c"
        src.write_text(_SHIM + ocl._KERNEL % {"big": BIG})
        so = tmp_path / f"k{tag}.so"
        subprocess.run(
            [
                "cc",
                "-O2",
                "-ffp-contract=off",
                "-shared",
                "-fPIC",
                "-w",
                f"-DMODEL={problem.model}",
                f"-DSCHEME={int(scheme == 'godunov')}",
                "-o",
                str(so),
                str(src),
                "-lm",
            ],
            check=True,
        )
        _agree(solve_numpy(problem, scheme), _solve_c(ctypes.CDLL(str(so)), problem, scheme))


def test_opencl_backend_error_is_one_line():
    from nirspi_pipe.errors import NirspiError
    from nirspi_pipe.sfs.models import LaxFriedrichsSFS
    from nirspi_pipe.types import Camera, Image2D

    img = np.zeros((8, 8))
    img[2:6, 2:6] = 1.0
    stage = LaxFriedrichsSFS(backend="opencl")
    if ocl.opencl_available():
        d = stage.solve(Image2D(img), Camera(resolution=8))
        assert d.info["backend"] == "opencl" and np.isfinite(d.depth_m).all()
    else:
        with pytest.raises(NirspiError, match="use sfs.backend=numpy"):
            stage.solve(Image2D(img), Camera(resolution=8))


#: Run in a fresh interpreter with empty kernel caches (PoCL's and pyopencl's): build the SFS
#: stages (their ``__post_init__`` warms the back end up), then solve each image twice, and list
#: what was compiled during the solves: programs built (pyopencl, the ``lru_cache`` misses of
#: ``_program``/``_program2``) and PoCL work-group functions (one ``<kernel>/<local size>/*.so``
#: in ``POCL_CACHE_DIR`` per kernel and local size, written at its first launch).
_FIRST_SOLVE = r"""
import json, os, sys, warnings
from pathlib import Path
warnings.simplefilter("ignore")
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sfs import opencl as ocl
from nirspi_pipe.sfs.models import LaxFriedrichsSFS, PerspectiveSFS
from nirspi_pipe.types import Camera, Image2D

if "no-warm-launch" in sys.argv:  # the code before issue 15: the build does not launch
    ocl._warm_launch = lambda *args: None
cache = Path(os.environ["POCL_CACHE_DIR"])
def compiled():
    return sorted(str(p.relative_to(cache)) for p in cache.rglob("*.so"))
def builds():
    return ocl._program.cache_info().misses + ocl._program2.cache_info().misses
images = {n: (Image2D(Sphere().render(Camera(resolution=n)).radiance), Camera(resolution=n)) for n in (32, 64)}
LaxFriedrichsSFS(scheme="godunov", backend="numpy").solve(*images[32])  # first calls outside OpenCL
stages = {s: LaxFriedrichsSFS(scheme=s, backend="opencl") for s in ("lax_friedrichs", "godunov", "second_order")}
stages["perspective"] = PerspectiveSFS(backend="opencl")
if "second-order-only" in sys.argv:
    stages = {"second_order": stages["second_order"]}
before, built = compiled(), builds()
backends = set()
for n, (img, cam) in images.items():
    for name, stage in stages.items():
        for _ in range(2):
            backends.add(stage.solve(img, cam).info["backend"])
print(json.dumps({"cached": sum(1 for p in cache.rglob("*") if p.is_file()), "new": sorted(set(compiled()) - set(before)),
                  "builds": builds() - built, "backends": sorted(backends)}))
"""


def first_solves(tmp_path, *args: str) -> dict:
    """Run :data:`_FIRST_SOLVE` with empty kernel caches under ``tmp_path``; its JSON report."""
    import json
    import os
    import sys

    env = dict(os.environ, POCL_CACHE_DIR=str(tmp_path / "pocl"), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    run = subprocess.run(
        [sys.executable, "-c", _FIRST_SOLVE, *args], env=env, capture_output=True, text=True, timeout=300, check=True
    )
    got = json.loads(run.stdout.strip().splitlines()[-1])
    if not got["cached"]:
        pytest.skip("the OpenCL platform here is not PoCL with its kernel cache: its compilations cannot be counted")
    return got


@pytest.mark.skipif(
    not (ocl.opencl_available() and ocl.opencl_available("second_order")),
    reason="no OpenCL device here builds float64 kernels",
)
def test_first_solve_after_build_costs_no_compilation(tmp_path):
    """Issue #15: compile time is never part of a stage's time. PoCL compiles a kernel's
    work-group function at its first launch with each local size, so building the program is
    not enough: the stage's build must launch it too (with empty caches the old code's first solve
    took 80–290 ms against 0.7–10 ms for the second; second order: 50 ms again at each new image
    size, from the driver-chosen local size of ``edges2``). Counted, not timed: solving 32² and
    64² images with every OpenCL scheme after the stages are built compiles no program and no
    work-group function (no new ``.so`` in PoCL's cache). The timing is ``nirspi-bench sfs``."""
    got = first_solves(tmp_path)
    assert got["backends"] == ["opencl"], got
    assert got["builds"] == 0 and got["new"] == [], f"the solves after the stages' build compiled: {got}"


@pytest.mark.skipif(
    not (ocl.opencl_available() and ocl.opencl_available("second_order")),
    reason="no OpenCL device here builds float64 kernels",
)
def test_the_compilation_count_sees_a_build_without_launch(tmp_path):
    """The count above can fail: with the build's warm launch removed (the code before issue
    15), the first solves compile a work-group function for each kernel they launch (the
    second-order stage's two kernels here, to keep it to one program build)."""
    got = first_solves(tmp_path, "no-warm-launch", "second-order-only")
    assert got["backends"] == ["opencl"], got
    assert {name.split("/")[2] for name in got["new"]} == {"fsm2", "edges2"}, got
