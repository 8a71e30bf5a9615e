"""Issue 36, the device-noise targets: a weighted average of ``completion`` and ``fista_tv``, the
weight fitted on held-out measurements (stacked regression: Wolpert 1992; Breiman 1996). A trial.

Both solvers run at their defaults on the whole acquisition (``x_c``, ``x_t``). Each is also fitted
to the training part of ``fista_tv``'s own hold-out split (:func:`~nirspi_pipe.solvers.crossval.holdout`):
the completion of the training measurements (the exponent the full data chose; zero-filled when
the guard fired) and ``fista_tv`` at the weight it chose on all the data. Their predictions ``p_c``,
``p_t`` of the held-out measurements ``y_H`` give the weight

    w = clip(⟨p_t − p_c, y_H − p_c⟩ / ‖p_t − p_c‖², 0, 1)

(least squares; the held-out noise is independent of both fits) and the image ``w x_t + (1 − w) x_c``.
Printed and written beside the two solvers and the oracle weight (the best ``w`` in [0, 1] by the
truth, closed form).

Result (the 9 tuning images only, zig-zag and cake-cutting, 10 / 25 / 50 %, device noise; 54
acquisitions; ``results/stacking_tuning.csv``): **not kept.** The held-out weight leans to TV (median
0.74 where the oracle's is 0.38; 0.35 apart per acquisition, median): median PSNR 24.29 / 24.54 /
24.25 dB against the completion's 24.31 / 24.64 / 24.70 (``fista_tv`` 24.17 / 23.88 / 23.51; the
oracle weight 24.37 / 24.72 / 24.80), and on 4 acquisitions more than 1 dB below the better of the two
(lfw_subset 10 % cake-cutting: w = 1.00, 1.91 dB below the completion). The held-out measurements
are interleaved with the training ones, where a TV fit predicts well; the unmeasured coefficients,
where the two differ, are not like them (``refine: tv``'s choice fails the same way). The oracle
weight gains only 0.06–0.10 dB median over the completion: the two images' errors are alike.

    python experiments/heldout/stacking.py --images chelsea coffee rocket hubble_deep_field \\
        immunohistochemistry retina logo colorwheel lfw_subset --orders zigzag cake_cutting --out stacking_tuning.csv
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

# the held-out benchmark's orders and simulators (a script's own folder is on sys.path)
from heldout_cs import IMAGES, ORDERS, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.patterns.hadamard import fwht
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.common import checked_coefficients
from nirspi_pipe.solvers.completion import CompletionSolver, complete
from nirspi_pipe.solvers.crossval import holdout
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.types import Acquisition, Camera

RESULTS = Path(__file__).parent / "results"


def stack(acq: Acquisition, truth: np.ndarray) -> dict[str, float]:
    n, idx = acq.n, np.asarray(acq.indices, dtype=np.int64)
    y = checked_coefficients(acq, "completion")
    solver = CompletionSolver()
    comp = solver.solve(acq)
    tv = FistaTVSolver().solve(acq)
    x_c, x_t = comp.data, tv.data
    train, held = holdout(y)
    sigma = float(comp.info["noise_sigma"])
    if float(comp.info.get("loo_ratio", 0.0)) > 1.0:  # guard fired: zero-filled
        xc_t = zero_filled_inverse(n, idx[train], y[train])
    else:
        chosen = [p for p in solver.priors() if p.alpha == comp.info["alpha"]]
        xc_t = complete(n, idx[train], y[train], sigma, chosen)[0]
    sub = Acquisition(n=n, indices=idx[train], y_pos=y[train])
    xt_t = FistaTVSolver(lam=float(tv.info["lam"])).solve(sub).data
    p_c = fwht(xc_t.ravel())[idx[held]]
    p_t = fwht(xt_t.ravel())[idx[held]]
    d = p_t - p_c
    w = float(np.clip(d @ (y[held] - p_c) / (d @ d), 0.0, 1.0)) if d @ d > 0 else 0.0
    e = (x_t - x_c).ravel()
    w_star = float(np.clip(e @ (truth - x_c).ravel() / (e @ e), 0.0, 1.0)) if e @ e > 0 else 0.0
    return {
        "completion": psnr(truth, x_c),
        "fista_tv": psnr(truth, x_t),
        "stack": psnr(truth, w * x_t + (1 - w) * x_c),
        "oracle": psnr(truth, w_star * x_t + (1 - w_star) * x_c),
        "w": w,
        "w_oracle": w_star,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", nargs="+", default=list(IMAGES))
    ap.add_argument("--orders", nargs="+", default=list(ORDERS), choices=list(ORDERS))
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.1, 0.25, 0.5])
    ap.add_argument("--noise", default="device", choices=["free", "device"])
    ap.add_argument("--out", default="stacking.csv")
    ns = ap.parse_args(argv)
    sim = simulator(ns.noise)
    cam = Camera(resolution=N)
    scenes = {name: ImageTarget(path=f"skimage:{name}").render(cam) for name in ns.images}
    rows = []
    for ratio in ns.ratios:
        for o in ns.orders:
            idx = ORDERS[o](ratio).select(N)
            t0 = time.perf_counter()
            for name, scene in scenes.items():
                acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
                row = {"image": name, "noise": ns.noise, "ratio": ratio, "order": o}
                rows.append(row | stack(acq, sim.reference_image(scene)))
            print(f"{ratio} {o}: {time.perf_counter() - t0:.0f} s", flush=True)
            pd.DataFrame(rows).to_csv(RESULTS / ns.out, index=False)
    frame = pd.DataFrame(rows)
    gain = frame[["completion", "stack", "oracle"]].sub(frame["fista_tv"], axis=0)
    print(frame.groupby("ratio")[["completion", "fista_tv", "stack", "oracle"]].median().round(2))
    print("stack − fista_tv by ratio: median, min\n", gain.groupby(frame["ratio"])["stack"].agg(["median", "min"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
