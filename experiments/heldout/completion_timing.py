"""Issue 36: time of ``solver=completion`` once its maps are cached, and of building them.

    OPENBLAS_NUM_THREADS=1 python experiments/heldout/completion_timing.py --out experiments/heldout/results

For each resolution, ratio and ``alpha`` setting (``auto``: three priors; the pooled fit alone), on
one acquisition of ``chelsea`` (a tuning image; the time does not depend on the image) at the
device's noise, zig-zag: the build (first solve minus a cached solve), then ``--repeat`` cached
solves (``CompletionSolver.solve``, the whole stage: checks, noise estimate, likelihood fits, the
products); median and fastest. Writes ``timing.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

# the held-out benchmark's cases; a script's own folder is on sys.path
from heldout_cs import md, simulator

from nirspi_pipe.patterns import orders as O
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers import completion as C
from nirspi_pipe.types import Camera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="experiments/heldout/results")
    ap.add_argument("--sizes", nargs="+", type=int, default=[8, 64])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.1, 0.25, 0.5])
    ap.add_argument("--repeat", type=int, default=51)
    ns = ap.parse_args(argv)
    sim = simulator("device")
    rows = []
    for n in ns.sizes:
        scene = ImageTarget(path="skimage:chelsea").render(Camera(resolution=n))
        for ratio in ns.ratios:
            acq = sim.acquire(scene, O.Zigzag(ratio).select(n), n, np.random.default_rng(0))
            for alpha in ("auto", C.default_prior().alpha):
                solver = C.CompletionSolver(alpha=alpha)
                C.clear_cache()
                t0 = time.perf_counter()
                solver.solve(acq)
                first = time.perf_counter() - t0
                times = []
                for _ in range(ns.repeat):
                    t0 = time.perf_counter()
                    solver.solve(acq)
                    times.append(time.perf_counter() - t0)
                ms = np.array(times) * 1e3
                rows.append(
                    {
                        "n": n, "ratio": ratio, "alpha": str(alpha), "build_s": first - np.median(times),
                        "cached_median_ms": float(np.median(ms)), "cached_fastest_ms": float(ms.min()),
                        "cache_MiB": sum(v.nbytes for v in C._CACHE.items.values()) / 2**20,
                    }
                )  # fmt: skip
                print(rows[-1], flush=True)
    t = pd.DataFrame(rows).set_index(["n", "ratio", "alpha"])
    text = f"# completion: build and cached solve ({ns.repeat} solves)\n\n{md(t)}\n"
    Path(ns.out, "timing.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
