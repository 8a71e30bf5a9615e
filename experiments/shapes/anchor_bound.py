"""What the paper's four iToF spots allow: an upper bound on the probability that issue 44's
chamfer targets are met at the iToF's default noise, even by a pipeline that recovers every
shape and its scale exactly.

    python experiments/shapes/anchor_bound.py [--resolution 64] [--shapes sphere,...,insect] [--seeds 10]
    python experiments/shapes/anchor_bound.py itof.averaging_s=8        # the iToF config to bound (overrides)

The argument, per shape:

1. **What a placement error costs.** ``c(δ)`` is the chamfer (mm, the project's own metric:
   :class:`~nirspi_pipe.mesh.metrics3d.Metrics3D` against the true surface) of the *exact* surface
   placed ``δ`` farther along every pixel's ray (``metric_floor.scores(depth_offset_m=δ)``): the
   reconstruction of a pipeline whose only error is the offset its anchoring fits. ``δ`` runs over
   a grid (``--step-mm``, ``--reach-mm``); ``S_t = {δ : c(δ) ≤ t}``, and ``|S_t|`` bounds its
   length from above: the grid's points in ``S_t`` plus one per run of them, times the step (a run
   of ``k`` grid points lies in an interval shorter than ``k + 1`` steps, assuming ``c`` does not
   dip below ``t`` and back between two grid points).
2. **What four spots can place.** Each spot reads the depth with Gaussian noise of at least the
   iToF's electronics floor ``σ = NED·sqrt(1/(2·averaging_s))`` (1 cm at the default 0.5 s;
   ``ContinuousWave4.sigma_floor_m``; shot noise only adds to it). From ``n`` such readings of a
   common offset, every placement that does not assume where the object is (shifting all readings
   by ``d`` shifts it by ``d``: the spots' mean, a median, the project's fit without its 1 % prior)
   has an error whose law does not depend on the true distance, and the best of them (Pitman's
   estimator, for Gaussian noise the mean) errs as ``N(0, σ²/n)``: ``σ_n = 5 mm`` for four spots at
   1 cm. By Anderson's lemma no set of length ``|S|`` holds more of a centred Gaussian than the
   centred interval, so each seed meets ``c ≤ t`` with probability at most
   ``q_t = P(|Z| ≤ |S_t|/2)``, ``Z ~ N(0, σ_n²)``, and the seeds (independent noise draws of the
   same scene) do so independently.
3. **The targets.** "No seed above 3 mm" over ``k`` seeds has probability at most ``q_3^k``; a
   median of ``k`` seeds at most 2 mm needs at least ``k/2`` of them at most 2 mm: probability at
   most ``P(Binomial(k, q_2) ≥ k/2)``. The target needs both: at most the smaller. The second
   target, fed the true depth within 1.5× the metric's floor ``c(0)``, is bounded the same way
   (its median: ``P(Binomial(k, q_f) ≥ k/2)`` with ``q_f`` from ``S_{1.5·c(0)}``): with the true
   depth the anchoring's offset is the only error left, which is exactly ``c(δ)``.

What it does not say: a pipeline with shape or scale errors is not bounded by this (its errors
could in principle partly cancel the offset's, which the bound does not rule out), and a method
that assumes the distance (a prior narrower than the working-distance uncertainty) is outside the
class in step 2; the fusion's prior (±25 % of the working distance) carries 1 % of the weight of
four spots. The numbers printed are ``c`` on the grid, ``|S_t|``, ``q_t`` and the bound.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parent))

import targets  # the thresholds and shapes (experiments/shapes/targets.py)

from nirspi_pipe.types import Camera

T2, T3 = targets.CHAMFER_TARGET_MM, targets.SEED_CEILING_MM


def itof_sigma_m(overrides: list[str]) -> tuple[float, int]:
    """``(σ per spot in metres, number of spots)`` of the iToF ``itof=cw4`` with ``overrides``
    (``itof.averaging_s=8``): the electronics floor, a lower bound on each spot's noise."""
    import nirspi_pipe
    from nirspi_pipe.instantiate import build

    cfg, _ = nirspi_pipe.compose(["itof=cw4", *overrides])
    itof = build(dict(cfg["itof"]), "itof")
    return float(itof.sigma_floor_m), int(itof.n_spots)


def chamfer_curve(model: object, camera: Camera, offsets_m: np.ndarray) -> np.ndarray:
    """``c(δ)`` (mm) of the exact surface moved ``δ`` along the rays, for each offset."""
    out = np.empty(len(offsets_m))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, d in enumerate(offsets_m):
            out[i] = targets.metric_floor.scores(model, camera, depth_offset_m=float(d))["chamfer_mm"]
    return out


def set_length(inside: np.ndarray, step: float) -> float:
    """Upper bound on the length of the set sampled as ``inside`` on a grid of ``step``: its
    points plus one per run of consecutive points, times the step (module docstring)."""
    inside = np.asarray(inside, dtype=bool)
    runs = int(np.sum(inside[1:] & ~inside[:-1])) + int(inside[0]) if len(inside) else 0
    return float(np.sum(inside) + runs) * step


def success_probability(length_m: float, sigma_m: float) -> float:
    """Anderson's bound: the most of ``N(0, σ²)`` any set of length ``length_m`` can hold."""
    if length_m <= 0:
        return 0.0
    return float(2.0 * stats.norm.cdf(length_m / (2.0 * sigma_m)) - 1.0)


def median_bound(q: float, seeds: int) -> float:
    """Upper bound on P(median of ``seeds`` values ≤ t), each ≤ t with probability at most ``q``:
    at least half of them must be."""
    return float(stats.binom.sf(int(np.ceil(seeds / 2)) - 1, seeds, q))


def target_bound(q2: float, q3: float, seeds: int) -> float:
    """Upper bound on P(median ≤ T2 and no seed > T3) over ``seeds`` independent seeds, each
    within ``T2`` with probability at most ``q2`` and within ``T3`` at most ``q3``."""
    return min(q3**seeds, median_bound(q2, seeds))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--shapes", default=",".join(targets.SHAPES))
    ap.add_argument("--seeds", type=int, default=10, help="seeds the target is judged over (issue 44: 10)")
    ap.add_argument("--step-mm", type=float, default=0.5, help="grid step of the offsets")
    ap.add_argument("--reach-mm", type=float, default=10.0, help="largest offset on the grid, either side")
    ap.add_argument("overrides", nargs="*", help="iToF overrides, e.g. itof.averaging_s=8")
    args = ap.parse_args(argv)
    sigma, spots = itof_sigma_m(args.overrides)
    sigma_n = sigma / np.sqrt(spots)
    step = args.step_mm * 1e-3
    offsets = np.arange(-args.reach_mm, args.reach_mm + args.step_mm / 2, args.step_mm) * 1e-3
    print(
        f"iToF {' '.join(args.overrides) or 'at its defaults'}: σ ≥ {sigma * 1e3:.2f} mm per spot, {spots} spots: "
        f"placement σ_n = {sigma_n * 1e3:.2f} mm; offsets ±{args.reach_mm:g} mm in steps of {args.step_mm:g} mm; "
        f"{args.seeds} seeds, {args.resolution}²"
    )
    print()
    print(
        "| shape | chamfer at δ = 0 / ±2.5 / ±5 mm (mm) | \\|S_2\\|, \\|S_3\\| (mm) | q_2, q_3 per seed | "
        f"P(target over {args.seeds} seeds) ≤ | true depth: \\|S_f\\| (mm), P(≤ {targets.FLOOR_RATIO:g}× floor) ≤ |"
    )
    print("|---|---|---|---|---|---|")
    camera = Camera(args.resolution)
    with tempfile.TemporaryDirectory() as tmp:
        for shape in args.shapes.split(","):
            c = chamfer_curve(targets.metric_floor.scene_model(shape, Path(tmp)), camera, offsets)
            at = {v: c[int(np.argmin(np.abs(offsets - v * 1e-3)))] for v in (0.0, -2.5, 2.5, -5.0, 5.0)}
            s2, s3 = set_length(c <= T2, step), set_length(c <= T3, step)
            edge = bool(c[0] <= T3 or c[-1] <= T3)  # S_3 reaches the grid's end: widen --reach-mm
            q2, q3 = success_probability(s2, sigma_n), success_probability(s3, sigma_n)
            bound = target_bound(q2, q3, args.seeds)
            sf = set_length(c <= targets.FLOOR_RATIO * at[0.0], step)  # c(0) is the metric's floor
            floor_bound = median_bound(success_probability(sf, sigma_n), args.seeds)
            print(
                f"| {shape} | {at[0.0]:.2f} / {at[-2.5]:.2f}, {at[2.5]:.2f} / {at[-5.0]:.2f}, {at[5.0]:.2f} "
                f"| {s2 * 1e3:.2f}, {s3 * 1e3:.2f}{' (grid end)' if edge else ''} | {q2:.3f}, {q3:.3f} | {bound:.2g} "
                f"| {sf * 1e3:.2f}, {floor_bound:.2g} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
