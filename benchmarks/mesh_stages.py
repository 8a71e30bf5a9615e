"""CPU time of the fusion and surface stages of the paper sweep's 3D jobs, step by step.

The paper sweep runs ``fusion=itof`` and ``surface=power_crust`` in its table3 and table4 jobs
(1280 of its 2608). This script runs a few of those jobs through :func:`nirspi_pipe.run`, keeps
each job's fusion and surface inputs, then calls the two stages on them again, ``--repeat`` times,
and prints the CPU time (``time.process_time``: a loaded machine's wall time says little) per job
of each stage and of its steps (the module functions each stage calls, wrapped for the count).
The kernels are warm (a first pass is not counted). Usage::

    python benchmarks/mesh_stages.py                         # 8 table3 jobs (4 objects x 5/15 kLux)
    python benchmarks/mesh_stages.py --experiment table4 --seeds 0,1 --save /tmp/caps.pkl
    python benchmarks/mesh_stages.py --load /tmp/caps.pkl    # the same inputs again

``--load`` reuses saved inputs, so two source trees compare on the same jobs: run it in this tree
and with ``PYTHONPATH=<other tree>/src`` in turn, a few times each (the medians of the totals).
With 72 table3/table4 jobs (seeds 0-2, scans basic, spiral, hilbert, zigzag) in the same process,
HEAD's modules (27f888e) against the changed ones alternating job by job: fusion 34-36 -> 27.4 ms
a job (bca1949, f59900d), surface 74.7 -> 70.2 ms (72efff1); see those commits' messages (issue 42
item 6). With this script, the default 8 jobs saved once and loaded by 27f888e's tree and by
72efff1's in turn, three runs each on a loaded 2-core machine: fusion 40.5-43.9 -> 29.0-32.4 ms,
surface 69.7-72.7 against 70.4-74.5 ms (within the noise of separate processes).
"""

from __future__ import annotations

import argparse
import collections
import itertools
import pickle
import time
import warnings
from collections.abc import Callable
from typing import Any

#: The module functions timed as steps of each stage (module path, names).
STEPS = {
    "fusion": (
        "nirspi_pipe.mesh.fusion",
        ("consistent_anchors", "heat_graph", "heat_step", "pca_normals", "remove_outliers", "semi_even_points"),
    ),
    "surface": (
        "nirspi_pipe.mesh.powercrust",
        ("compute_poles", "ConvexHull", "Delaunay", "crust_faces", "_label_view", "trim_to_samples")
        + ("remesh_to_cloud", "cloud_coverage", "_usable_samples", "sample_spacing"),
    ),
}


def capture(experiment: str, seeds: list[str], scans: list[str]) -> list[dict[str, tuple]]:
    """Run the jobs and keep each one's fusion ``(stage, depth, itof, camera)`` and surface
    ``(stage, cloud)`` inputs."""
    import nirspi_pipe  # start-up: loads the app (Hydra) only for capturing
    from nirspi_pipe.mesh.fusion import ItofFusion  # start-up: loads scipy
    from nirspi_pipe.mesh.powercrust import PowerCrust  # start-up: loads scipy and numba

    kept: dict[str, tuple] = {}
    fuse, reconstruct = ItofFusion.fuse, PowerCrust.reconstruct

    def fuse_kept(self: Any, depth: Any, itof: Any, camera: Any) -> Any:
        kept["fusion"] = (self, depth, itof, camera)
        return fuse(self, depth, itof, camera)

    def reconstruct_kept(self: Any, cloud: Any) -> Any:
        kept["surface"] = (self, cloud)
        return reconstruct(self, cloud)

    ItofFusion.fuse, PowerCrust.reconstruct = fuse_kept, reconstruct_kept  # type: ignore[method-assign]
    jobs = []
    try:
        for scene, klux, scan, seed in itertools.product(("sphere", "torus", "cube", "u_shape"), (5, 15), scans, seeds):
            kept.clear()
            nirspi_pipe.run(
                [
                    f"+experiment={experiment}",
                    f"scene={scene}",
                    f"illumination.klux={klux}",
                    f"scan={scan}",
                    f"seed={seed}",
                ]
            )
            jobs.append(dict(kept))
    finally:
        ItofFusion.fuse, PowerCrust.reconstruct = fuse, reconstruct  # type: ignore[method-assign]
    return jobs


def _timed(acc: collections.Counter, label: str, f: Callable[..., Any]) -> Callable[..., Any]:
    def run(*args: Any, **kwargs: Any) -> Any:
        t0 = time.process_time()
        try:
            return f(*args, **kwargs)
        finally:
            acc[label] += time.process_time() - t0

    return run


def profile(jobs: list[dict[str, tuple]], stage: str, repeat: int) -> None:
    """Print the stage's and its steps' CPU ms per job over ``repeat`` passes (one warm pass
    first, not counted)."""
    import importlib  # start-up: only for the step modules

    module = importlib.import_module(STEPS[stage][0])
    acc: collections.Counter = collections.Counter()
    names = [n for n in STEPS[stage][1] if hasattr(module, n)]
    originals = {n: getattr(module, n) for n in names}

    def one(job: dict[str, tuple]) -> None:
        stage_obj, *args = job[stage]
        (stage_obj.fuse if stage == "fusion" else stage_obj.reconstruct)(*args)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for job in jobs:
            one(job)
        for n in names:
            setattr(module, n, _timed(acc, n, originals[n]))
        try:
            t0 = time.process_time()
            for _ in range(repeat):
                for job in jobs:
                    one(job)
            total = time.process_time() - t0
        finally:
            for n, f in originals.items():
                setattr(module, n, f)
    count = repeat * len(jobs)
    print(f"{stage}: {1e3 * total / count:.2f} ms CPU a job ({len(jobs)} jobs x {repeat})")
    for name, seconds in acc.most_common():
        print(f"  {name:20s} {1e3 * seconds / count:7.2f} ms")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="table3", help="table3 (fog) or table4 (no fog); default table3")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument("--scans", default="basic", help="comma-separated scans (default basic)")
    ap.add_argument("--repeat", type=int, default=3, help="timed passes over the jobs (default 3)")
    ap.add_argument("--save", help="write the captured inputs to this pickle file")
    ap.add_argument("--load", help="read captured inputs (a file --save wrote; trusted: it is unpickled)")
    ns = ap.parse_args(argv)
    if ns.load:
        with open(ns.load, "rb") as fh:
            jobs = pickle.load(fh)  # the user's own file from --save (trusted)
    else:
        jobs = capture(ns.experiment, ns.seeds.split(","), ns.scans.split(","))
        if ns.save:
            with open(ns.save, "wb") as fh:
                pickle.dump(jobs, fh)
    for stage in ("fusion", "surface"):
        profile(jobs, stage, ns.repeat)


if __name__ == "__main__":
    main()
