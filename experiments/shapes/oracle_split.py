"""A 3D error split by stage with the oracle depth source ``sfs=truth`` (issue 44): a Markdown
table for docs/mesh.md.

    python experiments/shapes/oracle_split.py [--resolution 64] [--seeds 0-4] [--sfs second_order] [overrides…]

For each shape of the generated set (and the paper's sphere, torus and cube), noise-free by default
(ideal detector, no fog; the iToF at its default noise), runs ``itof=cw4 fusion=itof
surface=power_crust metrics=full`` twice per seed: with ``sfs=<sfs>`` and with ``sfs=truth``. It
prints the median over the seeds (and the largest value) of

* the fused depth RMSE with SFS and with the true depth (the second is what anchoring and fusion
  lose; the difference is SFS's share),
* the chamfer distance of the final mesh with the true depth (what the surface adds on top of its
  exact cloud: compare with the fused RMSE of the same run),
* the share of the fused cloud the power crust's mesh lies near (``info.surface.cloud_covered_fraction``;
  below 50 % the crust warns that it lost most of the shape).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import warnings

SHAPES = ("sphere", "plate_edge", "ring", "bowl", "multi", "partial", "off_centre", "vase", "torus", "cube")


def seeds_of(text: str) -> list[int]:
    """``0-4`` or ``0,3,7`` as a list of seeds."""
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-", 1))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


def base_overrides(resolution: int, seed: int) -> list[str]:
    """The noise-free study's overrides (``preset=off`` is ``preset=null``: no device preset), with
    the iToF at its default noise, scored by ``metrics=full``."""
    base = ["preset=off", "fog=none", "illumination=none", "detector=ideal", "itof=cw4", "fusion=itof"]
    return [*base, "surface=power_crust", "metrics=full", f"camera.resolution={resolution}", f"seed={seed}"]


def attempt(scene: list[str], sfs: str, seed: int, resolution: int, extra: list[str]) -> tuple[dict[str, float], str]:
    """The metrics that the split needs, of one run on the scene ``scene`` (its overrides), and ""
    or, where the run failed, NaN metrics and the reason in one line."""
    import nirspi_pipe

    nan = float("nan")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = nirspi_pipe.run([*base_overrides(resolution, seed), *scene, f"sfs={sfs}", *extra])
    except Exception as exc:  # noqa: BLE001 - a failed run is a row with its reason
        reason = f"{type(exc).__name__}: {exc}".splitlines()[0] if str(exc) else type(exc).__name__
        return {"fused": nan, "chamfer": nan, "covered": nan}, reason
    return {
        "fused": float(r.metrics.get("depth_rmse_fused_mm", nan)),
        "chamfer": float(r.metrics.get("chamfer_mm", nan)),
        "covered": float(r.info.get("surface", {}).get("cloud_covered_fraction", nan)),
    }, ""


def one(shape: str, sfs: str, seed: int, resolution: int, extra: list[str]) -> dict[str, float]:
    """The metrics that the split needs, of one run (NaN where the run failed; its reason on stderr)."""
    metrics, reason = attempt([f"scene={shape}"], sfs, seed, resolution, extra)
    if reason:
        print(f"  {shape} sfs={sfs} seed={seed}: {reason}", file=sys.stderr)
    return metrics


def summary(values: list[float], fmt: str) -> str:
    """Median over the seeds, and the largest value when there are several."""
    ok = [v for v in values if v == v]
    if not ok:
        return "failed"
    if len(ok) == 1:
        return fmt.format(ok[0])
    return f"{fmt.format(statistics.median(ok))} (≤ {fmt.format(max(ok))})"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--seeds", default="0-4")
    ap.add_argument("--sfs", default="second_order")
    ap.add_argument("--shapes", default=",".join(SHAPES))
    args, extra = ap.parse_known_args(argv)
    seeds = seeds_of(args.seeds)
    print(
        f"| shape | fused RMSE, sfs={args.sfs} (mm) | fused RMSE, sfs=truth (mm) | chamfer, sfs=truth (mm) "
        "| mesh near the cloud, sfs=truth |"
    )
    print("|---|---|---|---|---|")
    for shape in args.shapes.split(","):
        sfs = [one(shape, args.sfs, s, args.resolution, extra) for s in seeds]
        truth = [one(shape, "truth", s, args.resolution, extra) for s in seeds]
        print(
            f"| {shape} | {summary([r['fused'] for r in sfs], '{:.2f}')} | {summary([r['fused'] for r in truth], '{:.2f}')} "
            f"| {summary([r['chamfer'] for r in truth], '{:.2f}')} | {_cov(truth)} |",
            flush=True,
        )


def _cov(rows: list[dict[str, float]]) -> str:
    """Median covered share over the seeds, and the smallest."""
    ok = [100 * r["covered"] for r in rows if r["covered"] == r["covered"]]
    if not ok:
        return "failed"
    return f"{statistics.median(ok):.0f} %" + (f" (≥ {min(ok):.0f} %)" if len(ok) > 1 else "")


if __name__ == "__main__":
    main()
