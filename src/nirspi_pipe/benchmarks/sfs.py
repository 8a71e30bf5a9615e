"""``nirspi-bench sfs``: our fast-sweeping eikonal solvers against scikit-fmm's fast marching.

The problem is the SFS eikonal of an orthographic Lambertian sphere (radius 0.45·n pixels, light
at the viewer): ``|∇z| = F = sqrt(1/I² − 1)`` with ``I = sqrt(1 − r²/R²)``, ``F`` capped at
``I = 0.05`` outside the sphere (as the SFS stage does), and Dirichlet data ``z = z_true`` on the
circle through the brightest pixels' centres (our solvers: those pixels fixed; scikit-fmm: the
zero contour of ``φ = r − r_s``, speed ``1/F``). Both run in the same process on the same
``F``; errors are RMS against the analytic depth ``R − sqrt(R² − r²)`` over the sphere pixels
with ``I > 0.05``, in pixels. Target: time within 2× of scikit-fmm at equal or better error.

Solvers (``--schemes``): ``godunov`` and ``lax_friedrichs`` (first order), ``second_order``
(second-order upwind sweeping with slopes averaged along the upwind edges, cos²θ linear:
``sfs=second_order``) and ``second_order:node`` (the same with the pixel's own slope, i.e. fast
marching's order 2 swept: ``sfs=second_order sfs.slope_average=node``). Columns: time, sweeps,
RMS error, time ratios to scikit-fmm orders 2 and 1, and the error ratio to scikit-fmm order 2.

scikit-fmm is an optional extra: ``pip install 'nirspi-pipe[bench]'`` (or ``pip install
scikit-fmm``).
"""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.sfs.opencl import device_name, opencl_available, solve_opencl
from nirspi_pipe.sfs.sweeping import BIG, SweepProblem, SweepResult, solve_numpy

I_MIN = 0.05

#: ``--schemes`` names -> (scheme, slope_average).
SOLVERS = {
    "godunov": ("godunov", "cos2"),
    "lax_friedrichs": ("lax_friedrichs", "cos2"),
    "second_order": ("second_order", "cos2"),
    "second_order:node": ("second_order", "node"),
}


def sphere_problem(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """``(F, fixed, z_true, eval_mask, phi, z_source)`` of the sphere eikonal on an ``n × n`` grid."""
    radius = 0.45 * n
    c = np.arange(n) + 0.5 - n / 2.0
    r = np.hypot(c[None, :], c[:, None])
    inside = r < radius
    intensity = np.where(inside, np.sqrt(np.clip(1.0 - (r / radius) ** 2, 0.0, 1.0)), 0.0)
    f = np.sqrt(1.0 / np.maximum(intensity, I_MIN) ** 2 - 1.0)
    z_true = radius - np.sqrt(np.clip(radius**2 - r**2, 0.0, None))
    r_s = float(r.min())
    fixed = r <= r_s + 1e-9
    z_src = float(radius - np.sqrt(radius**2 - r_s**2))
    return f, fixed, z_true, inside & (intensity > I_MIN), r - r_s, z_src


def _rmse(z: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean((z - truth)[mask] ** 2)))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nirspi-bench sfs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--schemes", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    parser.add_argument("--backends", nargs="+", default=["numpy", "opencl"], choices=["numpy", "opencl"])
    parser.add_argument(
        "--device", default="auto", help="OpenCL device: auto, cpu, gpu or P:D (nirspi_pipe.opencl_devices)"
    )
    parser.add_argument(
        "--local-sizes",
        nargs="+",
        default=["device"],
        help="work-items of the OpenCL sweeping kernels: 'device' (what a stage uses: 1 on a CPU, the "
        "longest diagonal on a GPU) and/or numbers; each is one opencl row",
    )
    parser.add_argument("--no-fmm", action="store_true", help="skip scikit-fmm (and its ratio columns)")
    return parser


def _solvers(ns: argparse.Namespace) -> dict[str, Callable[..., SweepResult]]:
    """The solvers to time by row name: numpy, and one OpenCL row per ``--local-sizes`` where
    a device builds every scheme's kernels (its name printed)."""
    solvers: dict[str, Callable[..., SweepResult]] = {"numpy": solve_numpy}
    if "opencl" in ns.backends:
        needed = {SOLVERS[label][0] for label in ns.schemes}
        if all(opencl_available(scheme, ns.device) for scheme in needed):
            print(f"OpenCL device: {device_name(ns.device)}")
            for lsz in ns.local_sizes:
                local = None if lsz == "device" else int(lsz)
                key = "opencl" if lsz == "device" else f"opencl@{lsz}"
                solvers[key] = functools.partial(solve_opencl, local_size=local, device=ns.device)
    return solvers


def _fmm_rows(
    skfmm: Any, n: int, phi: np.ndarray, speed: np.ndarray, z_truth: tuple[np.ndarray, np.ndarray, float], repeat: int
) -> dict[int, tuple[float, float]]:
    """scikit-fmm's time and error per order (NaN without it), each printed as a row."""
    z_true, mask, z_src = z_truth
    refs = {2: (float("nan"), float("nan")), 1: (float("nan"), float("nan"))}
    for order in (2, 1) if skfmm is not None else ():
        t = median_time_s(lambda: skfmm.travel_time(phi, speed, order=order), repeat)
        z = np.abs(np.asarray(skfmm.travel_time(phi, speed, order=order))) + z_src
        refs[order] = (t, _rmse(z, z_true, mask))
        print(f"{n:>4}^2 {'scikit-fmm order ' + str(order):<26} {t * 1e3:>9.2f} {'-':>6} {refs[order][1]:>8.3f}")
    return refs


def _solver_row(
    n: int,
    name: str,
    run: Callable[[], SweepResult],
    repeat: int,
    truth: tuple[np.ndarray, np.ndarray],
    refs: dict[int, tuple[float, float]],
    best: dict[str, float] | None,
) -> None:
    """Times one solver, prints its row and records in ``best`` (None without scikit-fmm) whether
    it meets the target against each scikit-fmm order."""
    res = run()
    t = median_time_s(run, repeat)
    err = _rmse(res.z, *truth)
    r2, r1 = t / refs[2][0], t / refs[1][0]
    if best is not None:
        for order, ratio in ((2, r2), (1, r1)):
            key = f"{name} vs scikit-fmm order {order}"
            meets = ratio <= 2.0 and err <= refs[order][1] * (1 + 1e-9)
            best[key] = max(best.get(key, 0.0), 0.0 if meets else 1.0)
    print(
        f"{n:>4}^2 {name:<26} {t * 1e3:>9.2f} {res.sweeps:>6} {err:>8.3f} {r2:>7.2f} {r1:>7.2f}"
        f" {err / refs[2][1]:>7.3f}{'' if res.converged else '  (not converged)'}"
    )


def _size_rows(
    n: int, ns: argparse.Namespace, solvers: dict[str, Callable[..., SweepResult]], skfmm: Any, best: dict[str, float]
) -> None:
    """Every row of one size: scikit-fmm's orders, then each backend's schemes."""
    f, fixed, z_true, mask, phi, z_src = sphere_problem(n)
    refs = _fmm_rows(skfmm, n, phi, 1.0 / f, (z_true, mask, z_src), ns.repeat)
    problem = SweepProblem(f, fixed, np.where(fixed, z_true, BIG))
    names = [k for b in ns.backends for k in solvers if k == b or k.startswith(b + "@")]
    if "opencl" in ns.backends and not any(k.startswith("opencl") for k in solvers):
        print(f"{n:>4}^2 {'opencl':<26} unavailable: no OpenCL device builds float64 kernels here")
    for backend in names:
        for label in ns.schemes:
            scheme, slope = SOLVERS[label]
            run = functools.partial(solvers[backend], problem, scheme, 1e-4, 8000, slope_average=slope)
            repeat = 1 if scheme == "lax_friedrichs" else ns.repeat
            _solver_row(n, f"{label}/{backend}", run, repeat, (z_true, mask), refs, best if skfmm is not None else None)


def main(argv: list[str]) -> int:
    ns = _parser().parse_args(argv)
    skfmm: Any = None
    if not ns.no_fmm:
        try:
            import skfmm as _skfmm  # optional dependency: skfmm

            skfmm = _skfmm
        except ImportError:
            print(
                "nirspi-bench sfs: scikit-fmm is not installed; install it with\n"
                "    pip install 'nirspi-pipe[bench]'    (or: pip install scikit-fmm), or pass --no-fmm"
            )
            return 2
    solvers = _solvers(ns)
    ok_cl = any(k.startswith("opencl") for k in solvers)
    header = (
        f"{'size':>6} {'solver':<26} {'ms':>9} {'sweeps':>6} {'rmse px':>8} {'t/fmm2':>7} {'t/fmm1':>7} {'e/fmm2':>7}"
    )
    print(header)
    best: dict[str, float] = {}
    for n in ns.sizes:
        _size_rows(n, ns, solvers, skfmm, best)
    if skfmm is not None:
        print("target: time <= 2x scikit-fmm at equal or better RMS depth error")
    for key, v in best.items():
        print(f"  {key}: {'meets the target at every size' if v == 0.0 else 'misses the target'}")
    if not ok_cl and "opencl" in ns.backends:
        print("  opencl: not measured (no OpenCL device here builds float64 kernels)")
    return 0
