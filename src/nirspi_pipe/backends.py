"""Stages with more than one back end, declared in one place (issue 27: one parity harness).

Each :class:`Family` names a reference back end and its alternatives, the fixtures every back end
runs on, a comparison of two outputs as named discrepancies, and a bound on each discrepancy with
where that bound comes from. ``tests/test_parity.py`` runs every alternative of every family
against the reference on every fixture and checks every bound; a back end that cannot run here
(no OpenCL device, torch or pymeshlab not installed) is skipped with the reason
:meth:`Backend.unavailable` gives.

Plain data and functions: no configuration system, and every back end is imported only when it is
asked whether it is available or run, so importing this module costs nothing.

Adding a back end: add a :class:`Backend` to its family's ``alternatives`` (or a new
:class:`Family` to :data:`REGISTRY`), with its bounds measured on the family's fixtures.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh.remesh import clean_and_remesh, sample_spacing
from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.patterns.orders import ORDERS
from nirspi_pipe.solvers.omp_opencl import opencl_context
from nirspi_pipe.types import Acquisition, Image2D

__all__ = [
    "Backend",
    "Family",
    "REGISTRY",
    "SfsCase",
    "Tolerance",
    "blob_problem",
    "sfs_first_order_problems",
    "sfs_second_order_problems",
    "smooth_problem",
    "violations",
]


@dataclass(frozen=True)
class Backend:
    """One implementation of a stage.

    Attributes:
        name: short id (``numpy``, ``opencl``, ...), used in test ids.
        run: fixture → output (the output type is the family's).
        unavailable: None when the back end can run here, else the one-line reason it cannot.
        marks: pytest markers its parity cases carry (``torch``: deselected unless ``-m torch``).
    """

    name: str
    run: Callable[[Any], Any]
    unavailable: Callable[[], str | None]
    marks: tuple[str, ...] = ()

    def available(self) -> bool:
        """True when :attr:`unavailable` gives no reason."""
        return self.unavailable() is None


@dataclass(frozen=True)
class Tolerance:
    """Upper bound of one discrepancy (``compare``'s value must be ``<= bound``) and its source:
    what it was measured on and how, or which design requirement it states."""

    bound: float
    source: str


@dataclass(frozen=True)
class Family:
    """The back ends of one stage.

    Attributes:
        name: the stage family (``sfs``, ``omp``, ``fsrcnn``, ``remesh``).
        reference: the back end the others must agree with.
        alternatives: the other back ends.
        fixture_names: ids of the shared fixtures.
        make_fixture: fixture id → the input every back end's ``run`` takes.
        compare: ``(fixture, reference output, alternative output)`` → discrepancy by name; its
            keys are exactly those of ``tolerances``.
        tolerances: bound on each discrepancy.
    """

    name: str
    reference: Backend
    alternatives: tuple[Backend, ...]
    fixture_names: tuple[str, ...]
    make_fixture: Callable[[str], Any]
    compare: Callable[[Any, Any, Any], dict[str, float]]
    tolerances: Mapping[str, Tolerance] = field(default_factory=dict)


def violations(family: Family, fixture: Any, reference_out: Any, alternative_out: Any) -> list[str]:
    """Each discrepancy above its bound, as ``name = value > bound (source)``; empty when all hold.
    A discrepancy that ``compare`` gives without a bound (or a bound it does not give) is reported
    too, so that the two never drift apart."""
    got = family.compare(fixture, reference_out, alternative_out)
    out = [f"{k}: no stated tolerance" for k in sorted(set(got) - set(family.tolerances))]
    out += [f"{k}: not measured by compare" for k in sorted(set(family.tolerances) - set(got))]
    for key, tol in family.tolerances.items():
        if key in got and not got[key] <= tol.bound:  # NaN fails
            out.append(f"{key} = {got[key]:.3g} > {tol.bound:g} ({tol.source})")
    return out


# --- SFS: numpy (reference) and OpenCL fast sweeping -------------------------------------------


@dataclass(frozen=True)
class SfsCase:
    """One sweeping solve: the problem and the solver's arguments."""

    problem: Any  # nirspi_pipe.sfs.grid.SweepProblem
    scheme: str
    slope_average: str = "cos2"
    tol: float = 1e-4
    max_sweeps: int = 2000


def sfs_first_order_problems(n: int = 32) -> list[tuple[str, Any, str]]:
    """``(model, problem, scheme)``: the eikonal (Godunov and Lax–Friedrichs), the perspective
    model and the perspective model with fall-off on a shaded disc of side ``n``."""
    from nirspi_pipe.sfs.grid import BIG, SweepProblem  # start-up: loads 5 modules of ours (22 ms here)

    c = np.arange(n) + 0.5 - n / 2
    r = np.hypot(c[None, :], c[:, None])
    radius = 0.45 * n
    intensity = np.where(r < radius, np.sqrt(np.clip(1 - (r / radius) ** 2, 0, 1)), 0)
    f = np.sqrt(1 / np.maximum(intensity, 0.05) ** 2 - 1)
    fixed = r <= r.min() + 1e-9
    focal = 3.0 * n
    xh = yh = c / focal
    k = 1 / np.maximum(intensity, 0.05)
    w0 = 0.5 * focal * np.log(k * np.sqrt(1 + xh[None, :] ** 2 + yh[:, None] ** 2)) + 1
    return [
        ("eikonal", SweepProblem(f, fixed, np.where(fixed, 0.0, BIG)), "godunov"),
        ("eikonal", SweepProblem(f, fixed, np.where(fixed, 0.0, BIG)), "lax_friedrichs"),
        ("perspective", SweepProblem(k, fixed, np.where(fixed, 0.0, BIG), 1, xh, yh, focal), "lax_friedrichs"),
        ("falloff", SweepProblem(k, np.zeros_like(fixed), w0, 2, xh, yh, focal), "lax_friedrichs"),
    ]


def _grid(n: int) -> tuple[float, np.ndarray, np.ndarray]:
    length = n / 2.0
    c = (np.arange(n) + 0.5 - n / 2.0) / length
    return length, c[None, :] * np.ones((n, 1)), c[:, None] * np.ones((1, n))


def smooth_problem(n: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """``φ = x²/2 + y² + 0.3xy + 0.1x³``: one critical point (the origin), no contour, so
    ``z = Lφ`` is the viscosity solution of ``|∇z| = |∇φ|`` with ``z = 0`` there. Returns
    ``(L, z_true, F, evaluated)``."""
    length, x, y = _grid(n)
    phi = x * x / 2 + y * y + 0.3 * x * y + 0.1 * x**3
    f = np.hypot(x + 0.3 * y + 0.3 * x * x, 2 * y + 0.3 * x)
    return length, length * phi, f, np.ones_like(x, bool)


def blob_problem(n: int, k: float = 0.25) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """A closed smooth object with an occluding contour: ``z = c(1 − sqrt(1 − ρ))`` with
    ``ρ = (x/a)² + (y/b)² + k(x/a)³`` (an ellipsoid for ``k = 0``), seen with the light at the
    camera: ``F = tan θ``, capped at ``I = cos θ = 0.05`` as the SFS stage does. Evaluated where
    ``I > 0.05`` (the rim included). Returns ``(L, z_true, F, evaluated)``."""
    a, b, c = 0.8, 0.6, 0.7
    length, x, y = _grid(n)
    rho = (x / a) ** 2 + (y / b) ** 2 + k * (x / a) ** 3
    inside = rho < 1
    s = np.sqrt(np.clip(1 - rho, 1e-300, None))
    grad = np.hypot(2 * x / a**2 + 3 * k * x * x / a**3, 2 * y / b**2)
    f = np.where(inside, c / (2 * s) * grad, 1e9)
    cos = 1 / np.sqrt(1 + f * f)
    f = np.sqrt(1 / np.maximum(cos, 0.05) ** 2 - 1)
    return length, length * np.where(inside, c * (1 - s), 0.0), f, inside & (cos > 0.05)


def sfs_second_order_problems() -> dict[str, Any]:
    """Second-order agreement problems by name: a smooth problem without contour, two objects with
    an occluding contour, and random slopes with two Dirichlet cells."""
    from nirspi_pipe.sfs.grid import BIG, SweepProblem  # start-up: loads 5 modules of ours (22 ms here)

    out = {}
    kinds: dict[str, tuple[Callable[[int], tuple[float, np.ndarray, np.ndarray, np.ndarray]], int]] = {
        "smooth24": (smooth_problem, 24),
        "blob32": (blob_problem, 32),
        "ellipsoid17": (lambda n: blob_problem(n, 0.0), 17),
    }
    for name, (kind, n) in kinds.items():
        _, z_true, f, ev = kind(n)
        fixed = ev & (z_true <= z_true[ev].min() + 1e-12)
        out[name] = SweepProblem(f, fixed, np.where(fixed, z_true, BIG))
    f = np.random.default_rng(5).random((13, 21)) * 5
    fixed = np.zeros_like(f, bool)
    fixed[3, 4] = fixed[10, 15] = True
    out["random13x21"] = SweepProblem(f, fixed, np.where(fixed, 0.0, BIG))
    return out


_SFS_FIRST = ("eikonal-godunov", "eikonal-lax_friedrichs", "perspective-lax_friedrichs", "falloff-lax_friedrichs")
_SFS_SECOND = tuple(
    f"second_order-{slope}-{p}"
    for slope in ("cos2", "node")
    for p in ("smooth24", "blob32", "ellipsoid17", "random13x21")
)


def _sfs_fixture(name: str) -> SfsCase:
    if name in _SFS_FIRST:
        model, scheme = name.split("-")
        return next(
            SfsCase(problem, sch) for m, problem, sch in sfs_first_order_problems() if m == model and sch == scheme
        )
    _, slope, problem_name = name.split("-")
    return SfsCase(sfs_second_order_problems()[problem_name], "second_order", slope, 1e-4, 400)


def _sfs_numpy(case: SfsCase) -> Any:
    from nirspi_pipe.sfs.sweeping import solve_numpy  # start-up: loads 5 modules of ours (20 ms here)

    return solve_numpy(case.problem, case.scheme, case.tol, case.max_sweeps, slope_average=case.slope_average)


def _sfs_opencl(local_size: int | None) -> Callable[[SfsCase], Any]:
    def run(case: SfsCase) -> Any:
        from nirspi_pipe.sfs.opencl import solve_opencl  # start-up: loads 6 modules of ours (23 ms here)

        return solve_opencl(
            case.problem,
            case.scheme,
            case.tol,
            case.max_sweeps,
            local_size=local_size,
            slope_average=case.slope_average,
        )

    return run


def _sfs_opencl_unavailable() -> str | None:
    from nirspi_pipe.sfs.opencl import opencl_available  # start-up: loads 6 modules of ours (23 ms here)

    if opencl_available() and opencl_available("second_order"):
        return None
    return "no OpenCL device here builds the float64 sweeping kernels"


def _sfs_compare(case: SfsCase, a: Any, b: Any) -> dict[str, float]:
    return {
        "max_abs_z_px": float(np.max(np.abs(a.z - b.z))),
        "final_change_px": abs(a.final_change - b.final_change),
        "sweeps": float(abs(a.sweeps - b.sweeps)),
        "converged": float(a.converged != b.converged),
    }


_SFS_SOURCE = (
    "both back ends do the same operations in the same order (FP_CONTRACT off), only exp() of the "
    "fall-off model may differ in its last bits. Measured on these 12 fixtures with PoCL 3.1 (Debian, "
    "LLVM 15) on the CPU, local sizes 1, 8 and 64: identical bits except the fall-off model, max |dz| = "
    "1.4e-14 px there; the bound is that of the former per-twin tests. The cells of one anti-diagonal "
    "never read each other (Detrixhe, Gibou & Min 2013), so any number of work-items gives the same bits"
)

SFS = Family(
    name="sfs",
    reference=Backend("numpy", _sfs_numpy, lambda: None),
    alternatives=(
        Backend("opencl", _sfs_opencl(1), _sfs_opencl_unavailable),
        Backend("opencl-local8", _sfs_opencl(8), _sfs_opencl_unavailable),
        # a GPU's work-group: more work-items than the fixtures' longest diagonal (13-32 cells)
        Backend("opencl-local64", _sfs_opencl(64), _sfs_opencl_unavailable),
        # what a stage uses on this device (1 on a CPU, the longest diagonal on a GPU)
        Backend("opencl-device", _sfs_opencl(None), _sfs_opencl_unavailable),
    ),
    fixture_names=_SFS_FIRST + _SFS_SECOND,
    make_fixture=_sfs_fixture,
    compare=_sfs_compare,
    tolerances={
        "max_abs_z_px": Tolerance(1e-9, _SFS_SOURCE),
        "final_change_px": Tolerance(1e-9, _SFS_SOURCE),
        "sweeps": Tolerance(0, "the same arithmetic converges after the same number of sweeps"),
        "converged": Tolerance(0, "the same arithmetic converges after the same number of sweeps"),
    },
)


# --- OMP: numpy (reference) and OpenCL correlation/synthesis -----------------------------------


def _omp_scene(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] / n
    disc = ((yy - 0.5) ** 2 + (xx - 0.45) ** 2 < 0.1).astype(float)
    return np.clip(0.2 + 0.6 * disc * (1 - yy) + 0.05 * rng.random((n, n)), 0, 1)


@dataclass(frozen=True)
class OmpCase:
    """A Hadamard acquisition and the solver's settings."""

    acquisition: Any  # nirspi_pipe.types.Acquisition
    basis: str
    normalize: bool = False


_OMP_FIXTURES = ("dct-zigzag30", "haar-zigzag30", "dct-zigzag20-normalized")


def _omp_fixture(name: str) -> OmpCase:
    basis, order, *rest = name.split("-")
    n = 16
    img = _omp_scene(n)
    idx = np.asarray(ORDERS["zigzag"](ratio=int(order[len("zigzag") :]) / 100).select(n), dtype=np.int64)
    acq = Acquisition(n=n, indices=idx, y_pos=fwht2(img).ravel()[idx])
    return OmpCase(acq, basis, normalize=rest == ["normalized"])


def _omp(backend: str) -> Callable[[OmpCase], Any]:
    def run(case: OmpCase) -> Any:
        from nirspi_pipe.solvers.omp import OMPSolver  # start-up: loads scipy, charset_normalizer (220 ms here)

        return OMPSolver(basis=case.basis, backend=backend, normalize=case.normalize).solve(case.acquisition)

    return run


def _omp_device(mode: str) -> Callable[[OmpCase], Any]:
    """The device OMP laid out as ``mode`` (six kernels per atom, or one work-group per solve)."""

    def run(case: OmpCase) -> Any:
        # start-up: loads scipy, charset_normalizer (220 ms here)
        from nirspi_pipe.solvers.omp import (
            OMPSolver,
            omp_hadamard,
        )

        acq = case.acquisition
        y = acq.coefficients()
        image, info = omp_hadamard(
            y,
            acq.n,
            acq.indices,
            case.basis,
            OMPSolver().atoms(len(y)),
            OMPSolver().tol,
            "opencl",
            case.normalize,
            opencl_mode=mode,
        )
        return Image2D(image, info=info)

    return run


def _omp_opencl_unavailable() -> str | None:
    try:
        opencl_context()
    except NirspiError as exc:
        return str(exc)
    return None


def _omp_compare(case: OmpCase, a: Any, b: Any) -> dict[str, float]:
    return {
        "max_abs": float(np.max(np.abs(a.data - b.data))),
        "iterations": float(abs(a.info["iterations"] - b.info["iterations"])),
        "stop_reason": float(a.info["stop_reason"] != b.info["stop_reason"]),
    }


OMP = Family(
    name="omp",
    reference=Backend("numpy", _omp("numpy"), lambda: None),
    alternatives=(
        Backend("opencl", _omp("opencl"), _omp_opencl_unavailable),
        Backend("opencl-kernels", _omp_device("kernels"), _omp_opencl_unavailable),
        Backend("opencl-workgroup", _omp_device("workgroup"), _omp_opencl_unavailable),
    ),
    fixture_names=_OMP_FIXTURES,
    make_fixture=_omp_fixture,
    compare=_omp_compare,
    tolerances={
        "max_abs": Tolerance(
            1e-10,
            "float64 on both; the device sums the n-term products in another order than BLAS. Measured on "
            "these 3 fixtures (16x16 scene, values 0.2-0.8) with PoCL 3.1 (Debian) on the CPU: max |dx| = "
            "1.1e-16 (the host-driven kernels before issue 33, and the whole-solve-on-device ones after, "
            "both layouts). The former per-twin test allowed 1e-5",
        ),
        "iterations": Tolerance(0, "the same atoms are picked (measured: equal on every fixture)"),
        "stop_reason": Tolerance(0, "the same atoms are picked (measured: equal on every fixture)"),
    },
)


# --- FSRCNN inference: numpy (reference, float64) and torch (float32, as trained) --------------


@dataclass(frozen=True)
class FsrcnnCase:
    """A network and a low-resolution image."""

    weights: Any  # nirspi_pipe.upscale.fsrcnn.FsrcnnWeights
    image: np.ndarray
    #: ``trained-x…`` fixtures: the torch network of ``nirspi-train-fsrcnn`` (``upscale.train``)
    #: that ``weights`` were exported from; the torch back end runs it, so its export is checked too.
    module: Any = None


_FSRCNN_FIXTURES = (
    "shipped-x2",
    "shipped-x3",
    "shipped-x4",
    "random-x3-plain",
    "trained-x2",
    "trained-x3",
    "trained-x4",
)


def _fsrcnn_fixture(name: str) -> FsrcnnCase:
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        ConvLayer,
        FsrcnnWeights,
        load_weights,
    )

    kind, scale_s, *_ = name.split("-")
    scale = int(scale_s[1:])
    rng = np.random.default_rng(scale)
    yy, xx = np.mgrid[0:9, 0:11] / 10.0
    image = np.clip(0.5 + 0.3 * np.sin(6 * xx + 3 * yy) + 0.05 * rng.standard_normal((9, 11)), 0, 1)
    if kind == "shipped":
        return FsrcnnCase(load_weights(scale), image)
    if kind == "trained":  # a fresh network as nirspi-train-fsrcnn builds it, exported (needs torch)
        import torch  # optional dependency: torch

        # start-up: loads scipy, charset_normalizer (298 ms here)
        from nirspi_pipe.upscale.train import (
            _build_net,
            _to_weights,
        )

        torch.manual_seed(scale)
        net = _build_net(torch, scale, 6, 3, 2)
        return FsrcnnCase(_to_weights(net, scale, residual=False, border=6, meta={}), image, net)
    d, s = 6, 3  # (d, s, m) = (6, 3, 2), weights of order one so that rounding shows
    shapes = [(d, 1, 5), (s, d, 1), (s, s, 3), (s, s, 3), (d, s, 1)]
    layers = tuple(
        ConvLayer(
            rng.normal(0, 0.5, (o, i, k, k)).astype(np.float32),
            rng.normal(0, 0.1, o).astype(np.float32),
            rng.uniform(0.0, 0.5, o).astype(np.float32),
        )
        for o, i, k in shapes
    )
    deconv_w = rng.normal(0, 0.2, (d, 1, 9, 9)).astype(np.float32)
    return FsrcnnCase(FsrcnnWeights(scale, layers, deconv_w, np.array([0.1], np.float32), border=6), image)


def _fsrcnn_numpy(case: FsrcnnCase) -> np.ndarray:
    from nirspi_pipe.upscale.fsrcnn import fsrcnn_forward  # start-up: loads scipy, charset_normalizer (233 ms here)

    return fsrcnn_forward(case.image, case.weights)


def _fsrcnn_torch(case: FsrcnnCase) -> np.ndarray:
    """The network as ``nirspi-train-fsrcnn`` runs it: torch's float32 layers on the mirrored image
    (the training network itself for a ``trained`` fixture), cropped, plus the bicubic image for
    residual weights (upscale/train.py's own check), on the CPU."""
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        fsrcnn_forward_torch,
    )

    if case.module is None:
        return fsrcnn_forward_torch(case.image, case.weights, "cpu")
    import torch  # optional dependency: torch

    from nirspi_pipe.upscale.bicubic import bicubic  # start-up: loads scipy, charset_normalizer (200 ms here)

    w, s, pad = case.weights, case.weights.scale, case.weights.border
    x = torch.from_numpy(np.pad(case.image, pad, mode="symmetric").astype(np.float32))[None, None]
    with torch.no_grad():
        y = case.module(x)
    h, wd = case.image.shape
    out = y[0, 0].numpy().astype(np.float64)[pad * s : pad * s + h * s, pad * s : pad * s + wd * s]
    return out + bicubic(case.image, s) if w.residual else out


def _fsrcnn_torch_cuda(case: FsrcnnCase) -> np.ndarray:
    """:func:`_fsrcnn_torch` on CUDA with TF32 off (``upscale.device=cuda``, the default ``tf32: false``)."""
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        fsrcnn_forward_torch,
    )

    return fsrcnn_forward_torch(case.image, case.weights, "cuda", tf32=False)


def _cuda_unavailable() -> str | None:
    why = _torch_unavailable()
    if why is not None:
        return why
    import torch  # optional dependency: torch

    return None if torch.cuda.is_available() else "torch sees no CUDA GPU here"


def _torch_unavailable() -> str | None:
    try:
        # optional dependency: torch
        import torch  # noqa: F401 - only whether it imports
    except ImportError:
        return "torch is not installed (pip install 'nirspi-pipe[train]')"
    return None


def _fsrcnn_compare(case: FsrcnnCase, a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    return {"shape": float(a.shape != b.shape), "max_abs": float(np.max(np.abs(a - b))) if a.shape == b.shape else 1.0}


FSRCNN = Family(
    name="fsrcnn",
    reference=Backend("numpy", _fsrcnn_numpy, lambda: None),
    alternatives=(
        Backend("torch", _fsrcnn_torch, _torch_unavailable, marks=("torch",)),
        Backend("torch-cuda", _fsrcnn_torch_cuda, _cuda_unavailable, marks=("torch",)),
    ),
    fixture_names=_FSRCNN_FIXTURES,
    make_fixture=_fsrcnn_fixture,
    compare=_fsrcnn_compare,
    tolerances={
        "shape": Tolerance(0, "both crop to (h·scale, w·scale): the same output size"),
        "max_abs": Tolerance(
            1e-5,
            "torch runs in float32, numpy in float64; the cases include the trained-x2/x3/x4 fixtures "
            "(the training network against its exported weights). The float32 rounding it stands for, measured by "
            "running fsrcnn_forward's layers in float32 with numpy on these 4 fixtures: max |dy| = 1.6e-7 "
            "(shipped weights), 1.5e-6 (random net); torch 2.11 on an H200 with TF32 off: 1.5e-6 (with "
            "TF32 on: 1.3e-3, over the bound, hence upscale.tf32 false by default)",
        ),
    },
)


# --- Clean-up and isotropic remeshing: pymeshlab (reference) and the compiled twin -------------


@dataclass(frozen=True)
class RemeshCase:
    """A power-crust sheet of a noisy spherical cap and the cloud's sample spacing (metres)."""

    vertices: np.ndarray
    faces: np.ndarray
    spacing: float
    iterations: int = 3


_REMESH_FIXTURES = ("cap18-seed3", "cap14-seed0")


def _remesh_fixture(name: str) -> RemeshCase:
    # start-up: loads scipy, numba, charset_normalizer (466 ms here)
    from nirspi_pipe.mesh.powercrust import (
        power_crust,
        trim_to_samples,
    )

    cap, seed = name.split("-")
    n = int(cap[3:])
    rng = np.random.default_rng(int(seed[4:]))
    u, v = np.meshgrid(np.linspace(-0.7, 0.7, n), np.linspace(-0.7, 0.7, n))
    keep = u**2 + v**2 < 0.6
    u, v = u[keep], v[keep]
    pts = 0.025 * np.column_stack([u, v, -np.sqrt(1.0 - u**2 - v**2)]) + [0.0, 0.0, 0.2]
    pts = pts + rng.normal(0.0, 2e-5, pts.shape)
    sp = sample_spacing(pts)
    vv, ff, _ = power_crust(pts, "view", 3.0, 0.25, sp)
    vv, ff = trim_to_samples(vv, ff, pts, 1.5, sp)
    return RemeshCase(vv, ff, sp)


def _remesh_pymeshlab(case: RemeshCase) -> Any:
    return clean_and_remesh(case.vertices, case.faces, case.spacing, case.iterations)


def _remesh_compiled(case: RemeshCase) -> Any:
    from nirspi_pipe.mesh.isotropic import clean_and_remesh_compiled  # start-up: loads scipy, numba, yaml (204 ms here)

    return clean_and_remesh_compiled(case.vertices, case.faces, case.spacing, case.iterations)


def _pymeshlab_unavailable() -> str | None:
    try:
        # start-up: loads pymeshlab (134 ms here)
        import pymeshlab  # noqa: F401 - only whether it imports
    except ImportError as exc:
        return f"pymeshlab does not import ({exc})"
    return None


def _compiled_unavailable() -> str | None:
    from nirspi_pipe.mesh.isotropic import warm_up  # start-up: loads scipy, numba, yaml (204 ms here)

    return None if warm_up() else "numba could not compile the compiled remesher here"


def _remesh_compare(case: RemeshCase, ref: Any, alt: Any) -> dict[str, float]:
    from scipy.spatial import cKDTree  # start-up: loads scipy, charset_normalizer (255 ms here)

    # start-up: loads PIL, charset_normalizer, cycler (525 ms here)
    from nirspi_pipe.mesh.metrics3d import (
        equiangle_skewness,
    )

    (pv, pf, pinfo), (cv, cf, cinfo) = ref, alt
    if len(cf) == 0 or len(pf) == 0:
        return {k: float("inf") for k in _REMESH_TOLERANCES}
    return {
        "face_deficit": 1.0 - len(cf) / len(pf),
        "skewness_excess": float(equiangle_skewness(cv, cf).mean() - equiangle_skewness(pv, pf).mean()),
        "median_distance_to_reference_spacings": float(np.median(cKDTree(pv).query(cv)[0])) / case.spacing,
        "median_distance_from_reference_spacings": float(np.median(cKDTree(cv).query(pv)[0])) / case.spacing,
        "info_face_count_mismatch": float(
            abs(pinfo["faces_after_remesh"] - len(pf)) + abs(cinfo["faces_after_remesh"] - len(cf))
        ),
    }


_REMESH_SOURCE = (
    "a design bound, not a rounding error: the two remeshers are different algorithms (no feature "
    "edges, no reprojection in the compiled one). Bounds of the former "
    "test_compiled_remesher_matches_pymeshlab_on_a_power_crust; measured on these 2 fixtures "
    "(pymeshlab 2025.7, numba 0.68)"
)

_REMESH_TOLERANCES = {
    "face_deficit": Tolerance(0.5, _REMESH_SOURCE + ": 0.06 and 0.14"),
    "skewness_excess": Tolerance(0.02, _REMESH_SOURCE + ": -0.10 and -0.12 (the compiled meshes are better)"),
    "median_distance_to_reference_spacings": Tolerance(0.5, _REMESH_SOURCE + ": 0.29 and 0.29"),
    "median_distance_from_reference_spacings": Tolerance(0.5, _REMESH_SOURCE + ": 0.30 and 0.31"),
    "info_face_count_mismatch": Tolerance(0, "both report the face count they return"),
}

REMESH = Family(
    name="remesh",
    reference=Backend("pymeshlab", _remesh_pymeshlab, _pymeshlab_unavailable),
    alternatives=(Backend("compiled", _remesh_compiled, _compiled_unavailable),),
    fixture_names=_REMESH_FIXTURES,
    make_fixture=_remesh_fixture,
    compare=_remesh_compare,
    tolerances=_REMESH_TOLERANCES,
)


#: Every stage family with more than one back end, by name.
REGISTRY: dict[str, Family] = {f.name: f for f in (SFS, OMP, FSRCNN, REMESH)}
