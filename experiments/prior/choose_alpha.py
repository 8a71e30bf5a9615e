"""Issue 36: the prior's exponent chosen per acquisition (``alpha: auto``) against the pooled fit
alone, on the 9 tuning images of ``experiments/heldout`` (the design set; no held-out image).

    python experiments/prior/choose_alpha.py --noise device --ratio 0.25
    python experiments/prior/choose_alpha.py --noise free --ratio 0.25

Prints, per order and image, the PSNR of ``completion`` (no guard) under each shipped exponent,
the one the marginal likelihood picks, and the change against the pooled exponent alone.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "heldout"))

from heldout_cs import ORDERS, TUNING, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers import completion as C
from nirspi_pipe.solvers.noise import estimate_noise
from nirspi_pipe.types import Camera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--noise", default="device", choices=["free", "device"])
    ap.add_argument("--ratio", type=float, default=0.25)
    ap.add_argument("--orders", nargs="+", default=["zigzag", "cake_cutting"])
    ns = ap.parse_args(argv)
    sim = simulator(ns.noise)
    priors = C.CompletionSolver().priors()
    pooled = [p.alpha for p in priors].index(C.default_prior().alpha)
    changes = []
    for o in ns.orders:
        idx = ORDERS[o](ns.ratio).select(N)
        for name in TUNING:
            scene = ImageTarget(path=f"skimage:{name}").render(Camera(resolution=N))
            truth = sim.reference_image(scene)
            acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
            y, sigma = acq.coefficients(), estimate_noise(acq).sigma
            each = [psnr(truth, C.complete(N, idx, y, sigma, p)[0]) for p in priors]
            image, info = C.complete(N, idx, y, sigma, priors)
            chosen = psnr(truth, image)
            changes.append(chosen - each[pooled])
            cells = " ".join(f"α={p.alpha:g}: {v:.2f}" for p, v in zip(priors, each, strict=True))
            print(f"{o:13s} {name:21s} {cells}  chosen α={info['alpha']:g}: {chosen:.2f} ({changes[-1]:+.2f})")
    c = np.array(changes)
    print(f"change against the pooled exponent: median {np.median(c):+.2f}, min {c.min():+.2f}, max {c.max():+.2f} dB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
