"""``nirspi-bench render``: ray casting a ~10k-triangle mesh against the analytic sphere.

Both render the same Ø50 mm sphere at 20 cm in the same process, at the same resolution and
supersampling: the mesh scene (a pyvista UV sphere of ``--triangles`` triangles, written to a
PLY file and read back, the read cached) and the exact analytic sphere. The ratio mesh/analytic
is the cost of the general mesh path. Target: a 256² view of a ~10k-triangle mesh renders well
under 1 s (the absolute time is also printed), and the two images agree.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.scene.shapes import MeshScene
from nirspi_pipe.types import Camera


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench render", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--supersample", type=int, default=4)
    parser.add_argument("--triangles", type=int, default=10000, help="approximate mesh size")
    parser.add_argument("--repeat", type=int, default=5)
    ns = parser.parse_args(argv)
    import pyvista as pv  # start-up: loads pyvista (357 ms here)

    # a UV sphere has 2·θ·(φ − 2) triangles; θ = 2φ
    phi = max(4, int(round(np.sqrt(ns.triangles / 4.0))))
    mesh = pv.Sphere(radius=25.0, theta_resolution=2 * phi, phi_resolution=phi)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sphere.ply"
        mesh.save(str(path))
        scene = MeshScene(path=str(path), size_mm=50.0, supersample=ns.supersample)
        ref = Sphere(supersample=ns.supersample)
        print(f"mesh: {mesh.n_cells} triangles, supersample {ns.supersample}")
        print(f"{'size':>6} {'mesh ms':>10} {'sphere ms':>10} {'ratio':>7} {'max |Δradiance|':>16}")
        worst = 0.0
        for n in ns.sizes:
            cam = Camera(n)
            t_mesh = median_time_s(lambda: scene.render(cam), ns.repeat, min_time_s=0.0)
            t_ref = median_time_s(lambda: ref.render(cam), ns.repeat, min_time_s=0.0)
            diff = float(np.abs(scene.render(cam).radiance - ref.render(cam).radiance).max())
            worst = max(worst, t_mesh) if n >= 256 else worst
            print(f"{n:>4}^2 {t_mesh * 1e3:>10.1f} {t_ref * 1e3:>10.1f} {t_mesh / t_ref:>7.2f} {diff:>16.4f}")
    if worst:
        print(f"256^2 mesh render: {worst:.3f} s ({'meets' if worst < 1.0 else 'misses'} target < 1 s)")
    return 0
