"""Issue 36: the completion with the ``N × m`` map ``G = C Aᵀ V`` (cached until commit ``REV``)
against the current one (``C Aᵀ`` applied by transforms), on benchmark acquisitions.

    python experiments/heldout/map_equivalence.py            # needs git and the repository's history

Loads ``src/nirspi_pipe/solvers/completion.py`` as it was at ``REV`` (``git show``) beside the
installed one and solves the same acquisitions with both (camera, checkerboard, brick × basic,
zig-zag, random × 10 / 25 / 50 % × noise-free and device noise: 54): prints the largest pixel
difference and the range of the PSNR differences, and fails when the exponent or the guard's
decision differs. Then times both at 64², 50 %, ``alpha: auto`` (51 cached solves each, twice).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# the held-out benchmark's orders and simulators (a script's own folder is on sys.path)
from heldout_cs import ORDERS, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers import completion as new
from nirspi_pipe.types import Camera

REV = "754184f"
ROOT = Path(__file__).resolve().parents[2]


def load_old(rev: str):
    text = subprocess.run(
        ["git", "show", f"{rev}:src/nirspi_pipe/solvers/completion.py"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "completion_old.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("completion_old", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", default=REV)
    ns = ap.parse_args(argv)
    old = load_old(ns.rev)
    cam = Camera(resolution=N)
    worst, dpsnr = 0.0, []
    for noise in ("free", "device"):
        sim = simulator(noise)
        for ratio in (0.1, 0.25, 0.5):
            for o in ("basic", "zigzag", "random"):
                idx = ORDERS[o](ratio).select(N)
                for name in ("camera", "checkerboard", "brick"):
                    scene = ImageTarget(path=f"skimage:{name}").render(cam)
                    truth = sim.reference_image(scene)
                    acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
                    a, b = old.CompletionSolver().solve(acq), new.CompletionSolver().solve(acq)
                    if a.info["alpha"] != b.info["alpha"] or abs(a.info["loo_ratio"] - b.info["loo_ratio"]) > 1e-4:
                        raise SystemExit(f"{name} {o} {ratio} {noise}: {a.info} against {b.info}")
                    worst = max(worst, float(np.abs(a.data - b.data).max()))
                    dpsnr.append(psnr(truth, b.data) - psnr(truth, a.data))
    print(
        f"{len(dpsnr)} acquisitions: largest pixel difference {worst:.2e}, PSNR new − old {min(dpsnr):+.1e} … {max(dpsnr):+.1e} dB"
    )
    sim = simulator("device")
    idx = ORDERS["zigzag"](0.5).select(N)
    acq = sim.acquire(ImageTarget(path="skimage:chelsea").render(cam), idx, N, np.random.default_rng(0))
    for module in (old, new, old, new):
        solver = module.CompletionSolver()
        solver.solve(acq)
        times = []
        for _ in range(51):
            t0 = time.perf_counter()
            solver.solve(acq)
            times.append(time.perf_counter() - t0)
        print(f"{'old' if module is old else 'new'}: 64², 50 %, alpha auto, median {np.median(times) * 1e3:.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
