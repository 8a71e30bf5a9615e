"""Issue 36, step 3: ``completion`` with ``refine: tv`` (``fista_tv`` started from the completion
estimate) on the 15 held-out images, 64², 10 / 25 / 50 %, noise-free and at the device's noise, on
one order per image and setting: the order where plain ``completion`` did best in ``runs.csv`` (a
subset: the full run of every order did not fit the time). Compared with the best ``fwht`` and the
best ``fista_tv`` over every order (``runs.csv``), so the refinement is judged with one order against
the others' best of eight.

    python experiments/heldout/completion_tv.py --out experiments/heldout/results

Writes ``completion_tv.csv`` and ``completion_tv.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

# the held-out benchmark's images, orders and simulators; a script's own folder is on sys.path
from heldout_cs import IMAGES, ORDERS, N, md, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.completion import CompletionSolver
from nirspi_pipe.types import Camera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="experiments/heldout/results")
    ap.add_argument("--images", nargs="+", default=list(IMAGES))
    ap.add_argument("--tables-only", action="store_true", help="rewrite completion_tv.md from completion_tv.csv")
    ns = ap.parse_args(argv)
    out = Path(ns.out)
    if ns.tables_only:
        (out / "completion_tv.md").write_text(report(pd.read_csv(out / "completion_tv.csv")))
        return 0
    runs = pd.read_csv(out / "runs.csv")
    runs = runs[runs["image"].isin(ns.images)]
    key = ["image", "noise", "ratio"]
    comp = runs[runs["solver"] == "completion"]
    pick = comp.loc[comp.groupby(key)["psnr_db"].idxmax(), key + ["order", "psnr_db"]]
    best = {s: runs[runs["solver"] == s].groupby(key)["psnr_db"].max() for s in ("fwht", "fista_tv")}
    cam = Camera(resolution=N)
    solver = CompletionSolver(refine="tv")
    rows = []
    for (noise, ratio, order), group in pick.groupby(["noise", "ratio", "order"]):
        sim = simulator(noise)
        idx = ORDERS[order](ratio).select(N)
        for _, r in group.iterrows():
            scene = ImageTarget(path=f"skimage:{r['image']}").render(cam)
            acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
            t0 = time.perf_counter()
            img = solver.solve(acq)
            dt = time.perf_counter() - t0
            k = (r["image"], noise, ratio)
            rows.append(
                {"image": r["image"], "noise": noise, "ratio": ratio, "order": order,
                 "completion_tv": psnr(sim.reference_image(scene), img.data), "completion": r["psnr_db"],
                 "fista_tv_best": best["fista_tv"][k], "fwht_best": best["fwht"][k], "lam": img.info.get("lam"),
                 "seconds": dt}
            )  # fmt: skip
            print(rows[-1], flush=True)
    frame = pd.DataFrame(rows).sort_values(["noise", "ratio", "image"])
    frame.to_csv(out / "completion_tv.csv", index=False)
    (out / "completion_tv.md").write_text(report(frame))
    return 0


def report(frame: pd.DataFrame) -> str:
    """Per setting: medians, the targets' counts, and the images per setting."""
    lines = ["# completion, refine: tv (python experiments/heldout/completion_tv.py)", ""]
    counts = []
    for (noise, ratio), g in frame.groupby(["noise", "ratio"]):
        d_fwht = g["completion_tv"] - g["fwht_best"]
        d_tv = g["completion_tv"] - g["fista_tv_best"]
        counts.append(
            {"noise, sampling": f"{noise}, {ratio:.0%}", "images": len(g),
             "≥ fwht": int((d_fwht >= -1e-9).sum()), "≥ fwht + 1 dB": int((d_fwht >= 1).sum()),
             "median completion_tv / completion / fista_tv / fwht":
                 " / ".join(f"{g[c].median():.2f}" for c in ("completion_tv", "completion", "fista_tv_best", "fwht_best")),
             "< fista_tv − 1 dB": ", ".join(f"{i} ({v:.2f})" for i, v in zip(g["image"], d_tv) if v < -1) or "none",
             "median s": f"{g['seconds'].median():.2f}"}
        )  # fmt: skip
    lines += [md(pd.DataFrame(counts).set_index("noise, sampling")), ""]
    for (noise, ratio), g in frame.groupby(["noise", "ratio"]):
        lines += [
            f"## {noise}, {ratio:.0%}",
            "",
            md(g.drop(columns=["noise", "ratio"]).assign(lam=g["lam"].map(lambda v: f"{v:.2g}")).set_index("image")),
            "",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
