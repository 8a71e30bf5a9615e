"""Issue 36: how far can *any* stationary Gaussian prior take the completion on the held-out images?

The targets the shipped completion misses (docs/reconstruction.md, "The targets, on the held-out
images") are on textures and print noise-free and on piecewise-constant images at the device's noise.
This script asks whether a better prior of the same kind would meet them, by giving the completion
priors chosen *with the truth in hand* (oracles, not estimators: nothing here is usable on data):

* ``own``: the image's own second-order statistics: the stationary covariance whose spectrum is
  the image's periodogram on the ``2n × 2n`` torus (mean removed, zero-padded, ``|FFT|² / N``: the
  biased sample autocovariance, positive semi-definite; floored at ``FLOOR`` × its mean so that it
  is definite). The covariance a stationary prior would have if it were fitted to this one image.
* ``radial``: ``own`` averaged over rings of equal ``|f|`` (rounded to an integer number of cycles
  per image side): the image's own isotropic spectrum, what a radial profile fitted to this image
  would give at best.
* ``power_law``: every exponent of ``ALPHAS`` with the shipped roll-off ``f0``; the best per
  acquisition (chosen by PSNR against the truth).

And one prior that is *not* an oracle, for comparison (``--estimated``, its own run):

* ``estimated``: the spectrum the measurements themselves show: the periodogram of the zero-filled
  image (mean removed, ``2n`` torus), blurred by a Gaussian of ``BLUR`` frequency bins, plus the
  shipped power law at ``LAW_SHARE`` of the same total power (so that unmeasured frequencies keep a
  prior). Both numbers assumed: the first of four variants tried on six images (zig-zag, 25 %,
  noise-free; blur 1 or 2 bins, from the zero-filled image or from the shipped completion's), all
  within 0.2 dB of each other.

Each prior is used by the solver's own :func:`~nirspi_pipe.solvers.completion.complete` (guard off:
the oracle prior is trusted), on the benchmark's acquisitions (``heldout_cs.py``: same simulator,
same seed, every order), with the noise σ the solver estimates (``auto``) and, under noise, also the
best σ of ``heldout_cs.COMPLETION_GRID`` (``own_best_sigma``). The best order per image is compared
with the best ``fwht`` and the best ``fista_tv`` order of ``results/runs.csv``.

    python experiments/heldout/oracle_bound.py --settings free:0.25 device:0.1 device:0.25 --out-name oracle_bound_a
    python experiments/heldout/oracle_bound.py --settings device:0.5 --out-name oracle_bound_b
    python experiments/heldout/oracle_bound.py --settings free:0.25 --estimated --out-name oracle_bound_est
    python experiments/heldout/oracle_bound.py --tables-only

Writes ``results/oracle_bound*.csv`` (one row per image × setting × order × prior) and
``results/oracle_bound.md`` (the targets, best order per image).
"""

from __future__ import annotations

import argparse
import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

# the held-out benchmark's images, orders and simulators (a script's own folder is on sys.path)
from heldout_cs import COMPLETION_GRID, IMAGES, ORDERS, N, simulator
from scipy.ndimage import gaussian_filter

from nirspi_pipe.metrics import psnr
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.common import checked_coefficients
from nirspi_pipe.solvers.completion import PowerLawPrior, complete, default_prior, torus_convolve
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.solvers.noise import estimate_noise
from nirspi_pipe.types import Camera

#: Exponents of the power-law oracle (the shipped three lie in 2.46 … 6.0).
ALPHAS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0)
#: Floor of the own-spectrum prior, relative to its mean (assumed: keeps the covariance definite
#: without changing any frequency that carries 1e-6 of the mean power or more).
FLOOR = 1e-6
#: ``estimated``: blur of the periodogram, frequency bins, and the power law's share (module doc).
BLUR = 2.0
LAW_SHARE = 0.1
RESULTS = Path(__file__).parent / "results"


@dataclass(frozen=True)
class SpectrumPrior:
    """A stationary prior given by its spectrum on the ``2n × 2n`` torus (``(2n, 2n)``, unit mean:
    unit pixel variance); the interface :func:`complete` needs (``covariance_apply``,
    ``cache_key``, ``mean``)."""

    name: str
    spectrum: np.ndarray = field(repr=False)
    mean: float = 0.0

    @property
    def cache_key(self) -> tuple:
        return ("spectrum", self.name)

    def covariance_apply(self, images: np.ndarray) -> np.ndarray:
        return torus_convolve(images, self.spectrum[:, : images.shape[-1] + 1])


def own_prior(name: str, truth: np.ndarray) -> SpectrumPrior:
    """The image's periodogram on the ``2n`` torus as a prior (module doc)."""
    n = truth.shape[0]
    x = truth - truth.mean()
    p = np.abs(np.fft.fft2(x, s=(2 * n, 2 * n))) ** 2 / x.size
    p = p + FLOOR * p.mean()
    return SpectrumPrior(name=name, spectrum=p / p.mean(), mean=float(truth.mean()))


def radial_prior(own: SpectrumPrior) -> SpectrumPrior:
    """``own`` averaged over rings of equal rounded ``|f|`` (module doc)."""
    m = own.spectrum.shape[0]
    f = np.fft.fftfreq(m) * (m // 2)
    ring = np.rint(np.hypot(f[:, None], f[None, :])).astype(np.int64)
    profile = np.bincount(ring.ravel(), own.spectrum.ravel()) / np.bincount(ring.ravel())
    p = profile[ring]
    return SpectrumPrior(name=own.name + "-radial", spectrum=p / p.mean(), mean=own.mean)


def estimated_prior(name: str, n: int, idx: np.ndarray, y: np.ndarray) -> SpectrumPrior:
    """The spectrum the measurements show (module doc), from the data alone."""
    zero = zero_filled_inverse(n, idx, y)
    x = zero - zero.mean()
    p = gaussian_filter(np.abs(np.fft.fft2(x, s=(2 * n, 2 * n))) ** 2 / x.size, BLUR, mode="wrap")
    law = default_prior().spectrum(n)
    p = p + LAW_SHARE * law * (p.mean() / law.mean())
    return SpectrumPrior(name=name, spectrum=p / p.mean(), mean=default_prior().mean)


def run(settings: list[tuple[str, float]], images: list[str], orders: list[str], estimated: bool) -> pd.DataFrame:
    cam = Camera(resolution=N)
    base = default_prior()
    laws = [PowerLawPrior(alpha=a, f0=base.f0, mean=base.mean) for a in ALPHAS]
    scenes = {name: ImageTarget(path=f"skimage:{name}").render(cam) for name in images}
    rows = []
    for noise, ratio in settings:
        sim = simulator(noise)
        for o in orders:
            idx = ORDERS[o](ratio).select(N)
            t0 = time.perf_counter()
            for name, scene in scenes.items():
                truth = sim.reference_image(scene)
                acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
                y = checked_coefficients(acq, "completion")
                sigma = 0.0 if noise == "free" else float(estimate_noise(acq).sigma)
                key = hashlib.sha1(truth.tobytes() + y.tobytes()).hexdigest()[:12]
                row = {"image": name, "noise": noise, "ratio": ratio, "order": o, "sigma": sigma}
                if estimated:
                    row["estimated"] = psnr(truth, complete(N, idx, y, sigma, estimated_prior(key, N, idx, y))[0])
                    rows.append(row)
                    continue
                own = own_prior(f"{name}-{key}", truth)
                row["own"] = psnr(truth, complete(N, idx, y, sigma, own)[0])
                row["radial"] = psnr(truth, complete(N, idx, y, sigma, radial_prior(own))[0])
                law = [psnr(truth, complete(N, idx, y, sigma, p)[0]) for p in laws]
                row["power_law"] = max(law)
                row["power_law_alpha"] = ALPHAS[int(np.argmax(law))]
                if noise != "free":
                    row["own_best_sigma"] = max(
                        row["own"], *(psnr(truth, complete(N, idx, y, s, own)[0]) for s in COMPLETION_GRID)
                    )
                rows.append(row)
            print(f"{noise} {ratio} {o}: {time.perf_counter() - t0:.0f} s", flush=True)
    return pd.DataFrame(rows)


def tables(frame: pd.DataFrame, runs: pd.DataFrame) -> str:
    """The issue's targets with each oracle at its best order per image, against the best ``fwht``
    and ``fista_tv`` orders and the shipped completion's (``runs.csv``)."""
    best = runs[runs["set"] == "heldout"].groupby(["image", "noise", "ratio", "solver"])["psnr_db"].max().unstack()
    lines = [
        "# Oracle priors for the completion (issue 36)",
        "",
        "`python experiments/heldout/oracle_bound.py` (module doc). Each column at its best order per image;",
        "`fwht`, `fista_tv`, `completion`: the shipped solvers' best order (`runs.csv`). `own`: the image's own",
        "spectrum as the prior; `power_law`: the best exponent per acquisition (chosen with the truth);",
        "`radial`: its ring average; `own_best_sigma`: `own` at the best fixed σ too. dB.",
        "",
    ]
    for (noise, ratio), part in frame.groupby(["noise", "ratio"]):
        cols = [c for c in ("own", "radial", "power_law", "own_best_sigma", "estimated") if part[c].notna().any()]
        oracle = part.groupby("image")[cols].max()
        table = oracle.join(best.xs((noise, ratio), level=("noise", "ratio"))[["fwht", "fista_tv", "completion"]])
        table = table.loc[[i for i in IMAGES if i in table.index]]
        lines += [f"## {noise}, {ratio:.0%}", ""]
        head = ["image", *cols, "completion", "fista_tv", "fwht", "own − fwht", "own − fista_tv"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for img, r in table.iterrows():
            vals = [f"{r[c]:.2f}" for c in [*cols, "completion", "fista_tv", "fwht"]]
            vals += [f"{r['own'] - r['fwht']:+.2f}", f"{r['own'] - r['fista_tv']:+.2f}"]
            lines.append(f"| {img} | " + " | ".join(vals) + " |")
        med = table.median()
        lines += [
            "",
            "medians: " + ", ".join(f"{c} {med[c]:.2f}" for c in [*cols, "completion", "fista_tv", "fwht"]),
        ]
        for c in cols:
            gain = table[c] - table["fwht"]
            below = table[c] - table["fista_tv"]
            lines.append(
                f"- `{c}`: ≥ best fwht on {int((gain >= 0).sum())} of {len(table)}, ≥ +1 dB on "
                f"{int((gain >= 1).sum())}; median {'≥' if med[c] >= med['fista_tv'] else '<'} fista_tv's "
                f"({med[c] - med['fista_tv']:+.2f} dB); > 1 dB below fista_tv: "
                + (", ".join(f"{i} {v:+.2f}" for i, v in below[below < -1].items()) or "none")
            )
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--settings", nargs="+", default=["free:0.25", "device:0.1", "device:0.25", "device:0.5"])
    ap.add_argument("--images", nargs="+", default=list(IMAGES))
    ap.add_argument("--orders", nargs="+", default=list(ORDERS), choices=list(ORDERS))
    ap.add_argument("--out-name", default="oracle_bound")
    ap.add_argument("--estimated", action="store_true", help="only the prior estimated from the data (not an oracle)")
    ap.add_argument("--tables-only", action="store_true", help="rewrite oracle_bound.md from oracle_bound*.csv")
    ns = ap.parse_args(argv)
    if not ns.tables_only:
        settings = [(s.split(":")[0], float(s.split(":")[1])) for s in ns.settings]
        run(settings, ns.images, ns.orders, ns.estimated).to_csv(RESULTS / f"{ns.out_name}.csv", index=False)
    keys = ["image", "noise", "ratio", "order", "sigma"]
    frame = pd.DataFrame(columns=keys)
    for path in sorted(RESULTS.glob("oracle_bound*.csv")):
        frame = frame.merge(pd.read_csv(path), on=keys, how="outer", suffixes=("", "_dup"))
        for col in [c for c in frame if c.endswith("_dup")]:  # the same column from two runs
            frame[col[:-4]] = frame[col[:-4]].fillna(frame.pop(col))
    for col in ("own", "radial", "power_law", "own_best_sigma", "estimated"):
        frame[col] = frame[col] if col in frame else np.nan
    (RESULTS / "oracle_bound.md").write_text(tables(frame, pd.read_csv(RESULTS / "runs.csv")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
