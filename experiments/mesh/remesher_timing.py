"""Time the two remeshers on the same power crusts: the 16 Table 6 clouds (docs/mesh.md).

    OPENBLAS_NUM_THREADS=1 python experiments/mesh/remesher_timing.py [--passes 3]

Runs the 16 jobs of ``nirspi-run -m +experiment=table6 illumination.klux=5 seed=0`` in this
process (no files written), keeps each fused cloud, builds its power crust and trims it as
``surface=power_crust`` does (welded for remeshing), then times, on each crust, pymeshlab's
clean-up + 3 rounds of remeshing and the compiled clean-up and remeshing, ``--passes`` times over
the 16 crusts, and prints the medians with the mean final face count and equiangle skewness.
"""

from __future__ import annotations

import argparse
import itertools
import os
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--passes", type=int, default=3)
    ns = p.parse_args(argv)

    import nirspi_pipe
    from nirspi_pipe.mesh.isotropic import remesh_clean
    from nirspi_pipe.mesh.meshclean import clean_mesh
    from nirspi_pipe.mesh.metrics3d import equiangle_skewness
    from nirspi_pipe.mesh.powercrust import CLOUD_QUANTUM_M, PowerCrust, power_crust, trim_to_samples
    from nirspi_pipe.mesh.remesh import clean_and_remesh, sample_spacing

    stage = PowerCrust()  # builds: compiles or loads the kernels, imports nothing later
    weld = max(stage.weld_factor, 0.5 * min(stage.remesh_edge_factor, 1.0))
    crusts = []
    for scan, scene in itertools.product(
        ["basic", "hilbert", "zigzag", "spiral"], ["sphere", "torus", "cube", "u_shape"]
    ):
        r = nirspi_pipe.run(["+experiment=table6", f"scan={scan}", f"scene={scene}", "illumination.klux=5", "seed=0"])
        pts = np.round(np.asarray(r.products.cloud.points_m) / CLOUD_QUANTUM_M) * CLOUD_QUANTUM_M
        sp = sample_spacing(pts)
        v, f, _ = power_crust(pts, stage.labelling, stage.box_factor, weld, sp)
        v, f = trim_to_samples(v, f, pts, stage.trim_factor, sp)
        crusts.append((v, f, sp))
    times: dict[str, list[float]] = {"pymeshlab": [], "compiled clean-up": [], "compiled remeshing": []}
    faces: dict[str, list[int]] = {"pymeshlab": [], "compiled": []}
    skew: dict[str, list[float]] = {"pymeshlab": [], "compiled": []}
    for k in range(ns.passes):
        for v, f, sp in crusts:
            t = time.perf_counter()
            pv, pf, _ = clean_and_remesh(v, f, sp, 3)
            times["pymeshlab"].append(time.perf_counter() - t)
            t = time.perf_counter()
            cv, cf, _ = clean_mesh(v, f)
            times["compiled clean-up"].append(time.perf_counter() - t)
            t = time.perf_counter()
            cv, cf = remesh_clean(cv, cf, sp, 3)
            times["compiled remeshing"].append(time.perf_counter() - t)
            if k == 0:
                for name, vv, ff in (("pymeshlab", pv, pf), ("compiled", cv, cf)):
                    faces[name].append(len(ff))
                    skew[name].append(float(equiangle_skewness(vv, ff).mean()))
    print(f"16 Table 6 crusts x {ns.passes} passes, load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for name, ts in times.items():
        print(f"  {name:20s} median {np.median(ts) * 1e3:7.2f} ms")
    for name in faces:
        print(f"  {name:20s} faces {np.mean(faces[name]):7.0f}  mean equiangle skewness {np.mean(skew[name]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
