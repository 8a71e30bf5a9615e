"""``nirspi-bench paper``: where the time of a paper sweep goes, as ratios to a reference workload.

Runs ``nirspi-run -m +experiment=EXPERIMENT`` (default ``paper_ci``; ``--experiment paper`` for
the full sweep) in a fresh folder and splits its wall time:

* **keying**: composing every job's config and hashing it (the sweeper's loop, from its start to
  the moment it writes ``sweep.json``);
* **stages**: each pipeline stage's time summed over the jobs (``timings_ms.*`` in the records),
  and divided by the workers (the share of wall time, if perfectly parallel);
* **other**: the rest of the workers' time — the launcher, each job's own Hydra composition,
  imports in fresh workers, writing records and tables.

The reference workload, timed in the same process just before and after, is a fixed numpy task:
64² split-Hadamard simulation + fast inverse of the sphere, 50 times. It lasts only tens of
milliseconds, and one timing of it varied between 0.025 and 0.048 s in ten back-to-back timings
on the idle 2-core machine (2026-11-28), so each side takes the median of :data:`REFERENCE_REPEATS`
timings and the reference is the mean of the two medians; the smallest and largest single timing
are printed beside it. Every time is printed in seconds and as a multiple of the reference, which
is what to compare across runs on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from nirspi_pipe.patterns.orders import Basic
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.types import Camera

#: Timings of the reference workload on each side of the sweep (their median is used).
REFERENCE_REPEATS = 7


def reference_timings(repeats: int = REFERENCE_REPEATS) -> list[float]:
    """``repeats`` timings (seconds) of the fixed reference workload (see module doc)."""
    return [reference_s() for _ in range(repeats)]


def reference_s() -> float:
    """Seconds of the fixed reference workload, timed once (see module doc)."""
    from nirspi_pipe.solvers.fwht import FWHTSolver  # start-up: loads scipy and numpy (1366 ms here)
    from nirspi_pipe.sources.simulator import Simulator  # start-up: loads 18 modules of ours (37 ms here)

    scene = Sphere().render(Camera(resolution=64))
    idx = Basic(1.0).select(64)
    t0 = time.perf_counter()
    for k in range(50):
        FWHTSolver().solve(Simulator().acquire(scene, idx, 64, np.random.default_rng(k)))
    return time.perf_counter() - t0


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench paper", description=__doc__)
    parser.add_argument("--experiment", default="paper_ci")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="joblib n_jobs (default: all cores)")
    parser.add_argument("--dir", default=None, help="sweep folder (default: a temporary one)")
    ns = parser.parse_args(argv)
    import pandas as pd  # start-up: loads pandas and numpy (1118 ms here)

    cpu0 = os.times()
    ref_before = reference_timings()
    with tempfile.TemporaryDirectory() as tmp:
        sweep = Path(ns.dir or Path(tmp) / "sweep")
        exe = Path(sys.executable).with_name("nirspi-run")
        cmd = [
            str(exe),
            "-m",
            f"+experiment={ns.experiment}",
            f"hydra.sweep.dir={sweep}",
            f"hydra.launcher.n_jobs={ns.workers}",
        ]
        t0 = time.time()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        wall = time.time() - t0
        if proc.returncode != 0:
            print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
            return 1
        info = json.loads((sweep / "sweep.json").read_text())
        keying = float(info["keying_s"])  # the sweeper's own measure (sweep.json is written after it)
        frame = pd.read_parquet(sweep / "results.parquet")
    ref_after = reference_timings()
    ref = 0.5 * (float(np.median(ref_before)) + float(np.median(ref_after)))
    ref_lo, ref_hi = min(ref_before + ref_after), max(ref_before + ref_after)
    stages = {
        c.split(".", 1)[1]: float(frame[c].fillna(0).sum()) / 1e3
        for c in frame.columns
        if c.startswith("timings_ms.") and c != "timings_ms.total"
    }  # total = their sum
    total_stage = sum(stages.values())
    other = max(ns.workers * (wall - keying) - total_stage, 0.0)
    print(
        f"+experiment={ns.experiment}: {len(frame)} jobs run ({info['total']} in the grids), "
        f"{ns.workers} workers; reference workload {ref:.3f} s (median of {len(ref_before)} timings before and "
        f"{len(ref_after)} after, single timings {ref_lo:.3f}-{ref_hi:.3f} s)"
    )
    print(f"{'part':<22} {'seconds':>9} {'share of wall':>13} {'x reference':>11}")
    print(f"{'wall time':<22} {wall:>9.2f} {1.0:>13.2f} {wall / ref:>11.1f}")
    print(f"{'keying (sweeper)':<22} {keying:>9.2f} {keying / wall:>13.2f} {keying / ref:>11.1f}")
    for name, sec in sorted(stages.items(), key=lambda kv: -kv[1]):
        share = sec / ns.workers / wall
        print(f"{'stage ' + name:<22} {sec:>9.2f} {share:>13.2f} {sec / ref:>11.1f}")
    print(f"{'other (launch, jobs)':<22} {other:>9.2f} {other / ns.workers / wall:>13.2f} {other / ref:>11.1f}")
    cpu1 = os.times()
    cpu = (cpu1.children_user + cpu1.children_system) - (cpu0.children_user + cpu0.children_system)
    print(f"{'CPU of the sweep':<22} {cpu:>9.2f} {cpu / ns.workers / wall:>13.2f} {cpu / ref:>11.1f}")
    print(
        "(stage and other seconds are summed over the workers; their share divides by the workers; a CPU share"
        " well below 1 means the machine was shared)"
    )
    return 0
