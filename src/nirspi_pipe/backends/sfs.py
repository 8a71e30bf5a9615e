"""Shape from shading's back ends: numpy (reference) and OpenCL fast sweeping, their fixtures (the
first- and second-order test problems) and bounds (:data:`SFS`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.backends.harness import Backend, Family, Tolerance

__all__ = ["SFS", "SfsCase", "blob_problem", "sfs_first_order_problems", "sfs_second_order_problems", "smooth_problem"]


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
