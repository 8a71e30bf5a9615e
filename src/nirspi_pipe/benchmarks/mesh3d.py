"""``nirspi-bench mesh3d``: the whole 3D path at 64² against the paper's 147–168 ms (Table 6).

Times SFS (a stand-in from the ground truth unless ``--sfs NAME`` names a real sfs option),
iToF, fusion, surface and metrics on the default sphere, as one call each per repetition, and
reports the median per stage and in total. Reference measured in the same run: the 2D
reconstruction (``FWHTSolver.solve`` of the same acquisition) — the ratio says how many 2D
reconstructions the 3D path costs, which travels better between machines than milliseconds.
Target: total median < 50 ms (the paper's Jetson Nano: 146.5–167.5 ms).

On a loaded machine run it with ``OPENBLAS_NUM_THREADS=1``: OpenBLAS worker threads spinning
after a BLAS call steal the few cores and made single stages take seconds on our shared 2-core
box. The setting in force is printed.
"""

from __future__ import annotations

import argparse
import importlib
import os
import time

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.itof.cw4 import ContinuousWave4
from nirspi_pipe.mesh.remesh import clean_and_remesh, sample_spacing
from nirspi_pipe.mesh.standin import degraded_depth
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.stages import Products
from nirspi_pipe.types import Camera


def _load(target: str, backend: str | None):
    """An sfs stage from a config option name (``second_order``) or an import path."""
    if "." in target:
        module, _, name = target.rpartition(".")
        return getattr(importlib.import_module(module), name)()
    from hydra import compose, initialize_config_module  # start-up: loads hydra, omegaconf (118 ms here)

    from nirspi_pipe.pipeline import build  # start-up: loads 57 modules of ours (31 ms here)

    overrides = [f"sfs={target}"] + ([f"sfs.backend={backend}"] if backend else [])
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return build(cfg.sfs, "sfs")


def _remesher_ratio(cloud, surface, repeat: int) -> str:
    """Clean-up + remeshing of the last cloud's trimmed power crust by each implementation, in the
    same run: the compiled one against pymeshlab's (the reference)."""
    from nirspi_pipe.mesh.isotropic import clean_and_remesh_compiled  # start-up: loads scipy, numba, yaml (242 ms here)

    # start-up: loads scipy, numba, charset_normalizer (394 ms here)
    from nirspi_pipe.mesh.powercrust import (
        CLOUD_QUANTUM_M,
        PowerCrust,
        power_crust,
        trim_to_samples,
    )

    if not isinstance(surface, PowerCrust) or surface.remesh_iterations == 0:
        return ""
    try:
        # start-up: loads pymeshlab (94 ms here)
        import pymeshlab  # noqa: F401 - only whether it imports (not on every GPU machine)
    except ImportError:
        return "  (compiled / pymeshlab remeshing: not measured, pymeshlab is not installed)"
    pts = np.round(np.asarray(cloud.points_m) / CLOUD_QUANTUM_M) * CLOUD_QUANTUM_M
    sp = sample_spacing(pts)
    v, f, _ = power_crust(pts, surface.labelling, surface.box_factor, surface.weld_factor, sp)
    v, f = trim_to_samples(v, f, pts, surface.trim_factor, sp)
    args = (v, f, sp, surface.remesh_iterations, surface.remesh_edge_factor, surface.max_hole_edges)
    ref = median_time_s(lambda: clean_and_remesh(*args), repeat) * 1e3
    ours = median_time_s(lambda: clean_and_remesh_compiled(*args), repeat) * 1e3
    return (
        f"  clean-up + remeshing of the last crust ({len(f)} faces): compiled {ours:.2f} ms, "
        f"pymeshlab {ref:.2f} ms (reference); compiled / pymeshlab = {ours / ref:.2f}"
    )


def main(argv: list[str]) -> int:
    from nirspi_pipe.mesh.fusion import ItofFusion  # start-up: loads scipy, charset_normalizer (278 ms here)
    from nirspi_pipe.mesh.metrics3d import Metrics3D  # start-up: loads PIL, charset_normalizer, cycler (648 ms here)

    # start-up: loads scipy, numba, charset_normalizer (465 ms here)
    from nirspi_pipe.mesh.poisson import (
        ScreenedPoisson,
    )
    from nirspi_pipe.mesh.powercrust import PowerCrust  # start-up: loads scipy, numba, charset_normalizer (394 ms here)
    from nirspi_pipe.solvers.fwht import FWHTSolver  # start-up: loads scipy, charset_normalizer (197 ms here)
    from nirspi_pipe.sources.simulator import Simulator  # start-up: loads 24 modules of ours (61 ms here)

    parser = argparse.ArgumentParser(prog="nirspi-bench mesh3d", description=__doc__)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=15)
    parser.add_argument("--surface", choices=["power_crust", "poisson"], default="power_crust")
    parser.add_argument(
        "--sfs",
        default=None,
        help="an sfs config option (second_order, godunov, lax_friedrichs, …) or the "
        "import path of an sfs class (default: a stand-in from the truth)",
    )
    parser.add_argument(
        "--sfs-backend", default=None, choices=["auto", "numpy", "opencl"], help="sfs.backend for a config option"
    )
    parser.add_argument(
        "--remesher",
        default=None,
        choices=["auto", "compiled", "pymeshlab"],
        help="surface.remesher (default: the surface's own, auto)",
    )
    parser.add_argument(
        "--remesh-iterations",
        type=int,
        default=None,
        help="surface.remesh_iterations (default: the surface's own; 0 shows remeshing's price)",
    )
    ns = parser.parse_args(argv)

    cam = Camera(ns.resolution)
    scene = Sphere().render(cam)
    acq = Simulator().acquire(scene, np.arange(cam.resolution**2), cam.resolution, np.random.default_rng(0))
    solver = FWHTSolver()
    image = solver.solve(acq)
    itof = ContinuousWave4()
    fusion = ItofFusion()
    rkw: dict = {} if ns.remesh_iterations is None else {"remesh_iterations": ns.remesh_iterations}
    if ns.remesher is not None:
        rkw["remesher"] = ns.remesher
    surface = PowerCrust(**rkw) if ns.surface == "power_crust" else ScreenedPoisson(**rkw)
    metrics = Metrics3D()
    sfs = _load(ns.sfs, ns.sfs_backend) if ns.sfs else None

    def run_sfs():
        if sfs is not None:
            return sfs.solve(image, cam)
        return degraded_depth(scene, np.random.default_rng(1))

    stage_ms: dict[str, list[float]] = {k: [] for k in ("sfs", "itof", "fusion", "surface", "metrics", "total")}
    rng = np.random.default_rng(2)
    for i in range(ns.repeat + 1):
        t = [time.perf_counter()]
        depth = run_sfs()
        t.append(time.perf_counter())
        sample = itof.measure(scene, acq, rng)
        t.append(time.perf_counter())
        cloud = fusion.fuse(depth, sample, cam)
        t.append(time.perf_counter())
        mesh = surface.reconstruct(cloud)
        t.append(time.perf_counter())
        scores = metrics.compute(Products(scene, acq, image, None, depth, sample, cloud, mesh))
        t.append(time.perf_counter())
        if i == 0:
            continue  # warm-up (imports, caches)
        for k, (a, b) in zip(list(stage_ms)[:5], zip(t[:-1], t[1:])):
            stage_ms[k].append((b - a) * 1e3)
        stage_ms["total"].append((t[-1] - t[0]) * 1e3)
    ref_ms = median_time_s(lambda: solver.solve(acq), ns.repeat) * 1e3
    remesh_line = _remesher_ratio(cloud, surface, ns.repeat)
    med = {k: float(np.median(v)) for k, v in stage_ms.items()}
    sfs_name = (f"{ns.sfs}/{ns.sfs_backend or 'default'}") if ns.sfs else "stand-in (truth degraded)"
    print(
        f"3D path at {ns.resolution}^2, surface={ns.surface} (remesh_iterations={surface.remesh_iterations}), sfs={sfs_name}, {ns.repeat} repetitions (median ms), "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    for k, v in med.items():
        print(f"  {k:>8} {v:8.2f}")
    print(f"  reference: 2D reconstruction (fwht) {ref_ms:.3f} ms; 3D total / 2D = {med['total'] / ref_ms:.0f}")
    paper = (146.54, 167.53)
    print(
        f"  paper (Jetson Nano, Table 6): {paper[0]}-{paper[1]} ms; ours / paper = "
        f"{med['total'] / paper[1]:.2f}-{med['total'] / paper[0]:.2f}"
    )
    print(f"  target < 50 ms: {'met' if med['total'] < 50 else 'missed'}")
    if remesh_line:
        print(remesh_line)
    print(
        f"  last run: depth RMSE SFS {scores.get('depth_rmse_sfs_mm', float('nan')):.2f} mm -> fused "
        f"{scores.get('depth_rmse_fused_mm', float('nan')):.2f} mm, skewness {scores.get('skewness_mean', float('nan')):.2f}, "
        f"chamfer {scores.get('chamfer_mm', float('nan')):.2f} mm"
    )
    return 0
