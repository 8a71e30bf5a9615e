"""Issue 36, step 3, the quick check on the 9 tuning images (not the held-out ones): plain
``completion``, ``fista_tv`` and ``completion`` with ``refine: tv``, one order, ratio and noise.

    python experiments/heldout/completion_tv_tuning.py chelsea,coffee,... zigzag 0.25 free

Prints one line per image: PSNR dB, seconds and the TV weight.
"""

from __future__ import annotations

import sys
import time

import numpy as np

# the held-out benchmark's orders and simulators; a script's own folder is on sys.path
from heldout_cs import ORDERS, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.completion import CompletionSolver
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.types import Camera


def main() -> int:
    imgs, order, ratio, noise = sys.argv[1].split(","), sys.argv[2], float(sys.argv[3]), sys.argv[4]
    sim = simulator(noise)
    idx = ORDERS[order](ratio).select(N)
    for name in imgs:
        sc = ImageTarget(path=f"skimage:{name}").render(Camera(resolution=N))
        tr = sim.reference_image(sc)
        acq = sim.acquire(sc, idx, N, np.random.default_rng(0))
        out = []
        for lab, s in (
            ("comp", CompletionSolver()),
            ("tv", FistaTVSolver()),
            ("comp_tv", CompletionSolver(refine="tv")),
        ):
            t = time.perf_counter()
            im = s.solve(acq)
            dt = time.perf_counter() - t
            out.append(f"{lab} {psnr(tr, im.data):.2f} ({dt:.2f}s, lam={im.info.get('lam')})")
        print(name, order, ratio, noise, " | ".join(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
