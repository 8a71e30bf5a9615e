"""Issue 26: compare two versions of the ``fista_tv`` weight rule on scikit-image images that are
*not* among the 15 held-out ones of ``heldout_cs.py`` (the tuning set of the rule).

Run it once per version (a checkout's ``src`` on ``PYTHONPATH``), then compare:

    git worktree add /tmp/rule-old cf75066
    PYTHONPATH=/tmp/rule-old/src python experiments/heldout/tuning_images.py --out /tmp/old.csv
    python experiments/heldout/tuning_images.py --out /tmp/new.csv
    python experiments/heldout/tuning_images.py --compare /tmp/old.csv /tmp/new.csv

Images: chelsea, coffee, rocket, hubble_deep_field, immunohistochemistry, retina, logo, colorwheel,
lfw_subset (``binary_blobs`` is left out: scikit-image draws it anew on each call), 64², zig-zag,
cake-cutting and sequency at 10 and 25 %, noise-free and at the device's noise (as in
``heldout_cs.py``): 108 acquisitions, ``fista_tv`` at its defaults.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

# the held-out benchmark's two cases and size; a script's own folder is on sys.path
from heldout_cs import TUNING, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.patterns import orders as O
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.types import Camera

ORDERS = ("zigzag", "cake_cutting", "sequency")
RATIOS = (0.1, 0.25)


def run() -> pd.DataFrame:
    rows = []
    for name in TUNING:
        scene = ImageTarget(path=f"skimage:{name}").render(Camera(resolution=N))
        for case in ("free", "device"):
            sim = simulator(case)  # the held-out benchmark's two cases
            truth = sim.reference_image(scene)
            for ratio in RATIOS:
                for o in ORDERS:
                    acq = sim.acquire(scene, O.ORDERS[o](ratio).select(N), N, np.random.default_rng(0))
                    out = FistaTVSolver().solve(acq)
                    rows.append(
                        {"image": name, "noise": case, "ratio": ratio, "order": o,
                         "psnr_db": psnr(truth, out.data), "lam": out.info.get("lam")}
                    )  # fmt: skip
        print(name, flush=True)
    return pd.DataFrame(rows)


def compare(old: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """PSNR change per acquisition (new − old): count, mean, median, min, max per noise and ratio."""
    keys = ["image", "noise", "ratio", "order"]
    m = old.merge(new, on=keys, suffixes=("_old", "_new"))
    d = (m["psnr_db_new"] - m["psnr_db_old"]).rename("change_db")
    return (
        pd.concat([m[keys], d], axis=1)
        .groupby(["noise", "ratio"])["change_db"]
        .agg(["count", "mean", "median", "min", "max"])
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="write this version's results (CSV)")
    ap.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"), help="two CSVs from --out")
    ns = ap.parse_args(argv)
    if ns.compare:
        print(compare(pd.read_csv(ns.compare[0]), pd.read_csv(ns.compare[1])).round(2).to_string())
        return 0
    if not ns.out:
        ap.error("--out or --compare is required")
    run().to_csv(ns.out, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
