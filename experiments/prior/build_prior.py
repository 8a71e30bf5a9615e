"""Issue 36: rebuild the image prior of ``solver=completion`` from its training list, and compare it
with an empirical covariance of the same training set.

    python experiments/prior/build_prior.py                    # fit, write the package's JSON
    python experiments/prior/build_prior.py --compare          # + the comparison (minutes)

Training set (``training.txt``): images that ship with installed packages (no download) and are
none of the 24 images of ``experiments/heldout`` (15 held-out + 9 tuning scikit-image images). Each
is cut into square crops at three scales (the whole short side, a half and a quarter of it, on a grid
of half-crop steps, crops of fewer than ``n`` pixels left out) and their mirror images; each crop is
rendered at ``n²`` exactly as the benchmark renders its images (``ImageTarget`` on the ideal
simulator's reference image: the same sampling, reflectance and fall-off).

Fit: the mean periodogram of the mean-subtracted, Hann-windowed samples, radially averaged over
integer frequencies ``1 … n/2 − 1`` (cycles per image side), fitted in log scale by
``log P = c − (α/2)·log(f0² + f²)`` (scipy ``curve_fit``). The package ships ``α``, ``f0`` and the
mean radiance (``nirspi_pipe/data/completion_prior.json``, a few hundred bytes; the ``n²``
covariance is rebuilt from them on demand).

The exponent varies between images (smooth scenes steeper, textures flatter): the exponents fitted
to each crop alone give the spread, and the package also ships their 5th and 90th percentiles,
among which ``alpha: auto`` picks per acquisition by marginal likelihood.

``--compare``: the empirical covariance of the same samples (``N × N``, shrunk towards a scaled
identity by the Ledoit–Wolf 2004 weight; 128 MiB at 64², built here, never shipped) against the
power law, as priors of the same completion, on the 9 tuning images of ``experiments/heldout``
(zig-zag and cake-cutting, 10 / 25 / 50 %, noise-free and at the device's noise); the result is
written into the JSON (``comparison``).
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import curve_fit

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
OUT = ROOT / "src" / "nirspi_pipe" / "data" / "completion_prior.json"
sys.path.insert(0, str(ROOT / "experiments" / "heldout"))

from heldout_cs import ORDERS, TUNING, simulator  # noqa: E402

from nirspi_pipe.metrics import psnr  # noqa: E402
from nirspi_pipe.scene.objects import ImageTarget  # noqa: E402
from nirspi_pipe.solvers import completion as C  # noqa: E402
from nirspi_pipe.solvers.fwht import FWHTSolver  # noqa: E402
from nirspi_pipe.solvers.noise import estimate_noise  # noqa: E402
from nirspi_pipe.types import Camera  # noqa: E402

#: Crop sides as fractions of the image's short side.
SCALES = (1.0, 0.5, 0.25)
#: ``alpha: auto`` chooses among the pooled fit and these percentiles of the exponents fitted to each
#: crop alone (the spread of the training set; the fit is bounded to α ≤ 6).
ALPHA_PERCENTILES = (5, 90)


def training_list(path: Path = HERE / "training.txt") -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def load(entry: str) -> np.ndarray:
    """A training image, grey, in [0, 1]."""
    import matplotlib
    from PIL import Image
    from skimage import color, data

    source, _, rest = entry.partition(":")
    name, _, key = rest.partition(":")
    if source == "skimage":
        img = getattr(data, name)()
        if isinstance(img, tuple):
            img = img[int(key or 0)]
    elif source == "mpl":
        file = Path(matplotlib.get_data_path()) / "sample_data" / name
        if name.endswith(".npz"):
            img = np.load(file)[key]
        elif name.endswith(".ima.gz"):  # matplotlib's MRI slice: 256 × 256 uint16 (its own examples)
            with gzip.open(file) as f:
                img = np.frombuffer(f.read(), np.uint16).reshape(256, 256)
        else:
            img = np.asarray(Image.open(file))
    else:
        raise ValueError(f"{entry}: source must be skimage: or mpl:")
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 3:
        img = color.rgb2gray(img[..., :3] / (255.0 if img.max() > 1 else 1.0))
    lo, hi = float(img.min()), float(img.max())
    return (img - lo) / (hi - lo)


def crops(img: np.ndarray, n: int) -> list[np.ndarray]:
    """Square crops at ``SCALES`` of the short side on a half-crop grid (module doc), and mirrors."""
    h, w = img.shape
    out = []
    for frac in SCALES:
        side = int(min(h, w) * frac)
        if side < n:
            continue
        step = max(side // 2, 1)
        rows = sorted({*range(0, h - side + 1, step), h - side})
        cols = sorted({*range(0, w - side + 1, step), w - side})
        for r in rows:
            for c in cols:
                sq = img[r : r + side, c : c + side]
                out += [sq, sq[:, ::-1]]
    return out


def render(samples: list[np.ndarray], n: int) -> np.ndarray:
    """``(S, n, n)``: each crop rendered as the benchmark renders its images (16-bit PNG →
    ``ImageTarget`` → the ideal simulator's reference image)."""
    from PIL import Image

    cam = Camera(resolution=n)
    sim = simulator("free")
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, sq in enumerate(samples):
            file = Path(tmp) / f"{k}.png"
            Image.fromarray(np.round(sq * 65535).astype(np.uint16)).save(file)
            out.append(sim.reference_image(ImageTarget(path=str(file)).render(cam)))
    return np.stack(out)


def fit_power_law(x: np.ndarray) -> dict[str, float]:
    """``α``, ``f0`` of the mean radial periodogram (module doc), and the fit's rms log error."""
    s, n, _ = x.shape
    win = np.outer(np.hanning(n), np.hanning(n))
    v = (x - x.mean(axis=(1, 2), keepdims=True)) * win
    p = np.mean(np.abs(np.fft.fft2(v)) ** 2, axis=0)
    f = np.fft.fftfreq(n) * n
    r = np.rint(np.hypot(f[:, None], f[None, :])).astype(int)
    radii = np.arange(1, n // 2)
    prof = np.array([p[r == k].mean() for k in radii])

    def model(f: np.ndarray, c: float, alpha: float, f0: float) -> np.ndarray:
        return c - 0.5 * alpha * np.log(f0**2 + f**2)

    popt, _ = curve_fit(model, radii.astype(float), np.log(prof), p0=(np.log(prof[0]), 2.0, 1.0),
                        bounds=([-np.inf, 0.0, 1e-3], [np.inf, 6.0, n / 2]))  # fmt: skip
    resid = np.log(prof) - model(radii, *popt)
    return {"alpha": float(popt[1]), "f0": float(popt[2]), "rms_log_error": float(np.sqrt(np.mean(resid**2)))}


def _textured(img: np.ndarray) -> bool:
    """Whether a sample has power at every radius of the fit (a flat crop, e.g. sky, has not)."""
    n = img.shape[-1]
    p = np.abs(np.fft.fft2(img - img.mean())) ** 2
    f = np.fft.fftfreq(n) * n
    r = np.rint(np.hypot(f[:, None], f[None, :])).astype(int)
    return all(p[r == k].mean() > 0 for k in range(1, n // 2))


@dataclass(eq=False)
class EmpiricalPrior:
    """A full ``N × N`` covariance as a completion prior (comparison only)."""

    cov: np.ndarray
    mean: float

    @property
    def cache_key(self) -> tuple:
        return ("empirical", id(self))

    def covariance_apply(self, images: np.ndarray) -> np.ndarray:
        b, n, _ = images.shape
        return (images.reshape(b, n * n) @ self.cov).reshape(b, n, n)


def ledoit_wolf(x: np.ndarray) -> tuple[np.ndarray, float]:
    """Sample covariance of the rows of ``x`` (``S × N``) shrunk to ``(tr/N) I`` with Ledoit &
    Wolf's (2004) weight; returns it and the weight."""
    s, d = x.shape
    xc = x - x.mean(axis=0)
    cov = xc.T @ xc / s
    mu = np.trace(cov) / d
    delta = np.sum((cov - mu * np.eye(d)) ** 2) / d
    # Σₖ ‖xₖxₖᵀ − S‖² = Σₖ ‖xₖ‖⁴ − s‖S‖² (S the mean of the xₖxₖᵀ); their eq. for β̄ divides by s²
    beta_bar = (np.sum(np.sum(xc * xc, axis=1) ** 2) - s * np.sum(cov * cov)) / s**2
    beta = min(delta, beta_bar / d)
    rho = beta / delta if delta > 0 else 1.0
    cov *= 1.0 - rho
    cov[np.diag_indices(d)] += rho * mu
    return cov, float(rho)


def compare(priors: dict[str, object], n: int) -> list[dict[str, object]]:
    """PSNR of the completion under each prior (and ``fwht``) on the tuning images (module doc)."""
    rows = []
    cam = Camera(resolution=n)
    for noise in ("free", "device"):
        sim = simulator(noise)
        for name in TUNING:
            scene = ImageTarget(path=f"skimage:{name}").render(cam)
            truth = sim.reference_image(scene)
            for ratio in (0.1, 0.25, 0.5):
                for o in ("zigzag", "cake_cutting"):
                    idx = ORDERS[o](ratio).select(n)
                    acq = sim.acquire(scene, idx, n, np.random.default_rng(0))
                    y = acq.coefficients()
                    sigma = estimate_noise(acq).sigma
                    row = {"image": name, "noise": noise, "ratio": ratio, "order": o,
                           "fwht": psnr(truth, FWHTSolver().solve(acq).data)}  # fmt: skip
                    for label, prior in priors.items():
                        row[label] = psnr(truth, C.complete(n, idx, y, sigma, prior)[0])  # type: ignore[arg-type]
                    rows.append(row)
        print(f"compare {noise} done", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64, help="resolution of the fit (pixels per side)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--compare", action="store_true", help="also compare with the empirical covariance")
    ns = ap.parse_args(argv)
    entries = training_list()
    samples = [c for e in entries for c in crops(load(e), ns.n)]
    x = render(samples, ns.n)
    fit = fit_power_law(x)
    prior = C.PowerLawPrior(alpha=round(fit["alpha"], 4), f0=round(fit["f0"], 4), mean=round(float(x.mean()), 4))
    per_crop = np.array([fit_power_law(x[k : k + 1])["alpha"] for k in range(len(x)) if _textured(x[k])])
    lo, hi = (round(float(v), 4) for v in np.percentile(per_crop, ALPHA_PERCENTILES))
    doc = {
        "what": "solver=completion's image prior: power spectrum (f0^2 + f^2)^(-alpha/2), f in cycles per "
        "image side; mean: prior mean radiance (relative), used when DC is not measured",
        "command": "python experiments/prior/build_prior.py" + (" --compare" if ns.compare else ""),
        "prior": {"alpha": prior.alpha, "f0": prior.f0, "mean": prior.mean, "alphas": [lo, prior.alpha, hi]},
        "fit": {
            **fit,
            "n": ns.n,
            "samples": int(len(x)),
            "samples_fitted_alone": int(per_crop.size),
            "alpha_per_crop_percentiles": {
                str(q): round(float(np.percentile(per_crop, q)), 3) for q in (5, 10, 25, 50, 75, 90, 95)
            },
        },
        "training": entries,
    }
    print(json.dumps(doc["prior"]), doc["fit"], flush=True)
    if ns.compare:
        cov, rho = ledoit_wolf(x.reshape(len(x), -1))
        rows = compare({"power_law": prior, "empirical": EmpiricalPrior(cov, prior.mean)}, ns.n)  # pooled α
        import pandas as pd

        t = pd.DataFrame(rows)
        summary = t.groupby(["noise", "ratio"])[["fwht", "power_law", "empirical"]].median().round(2)
        wins = (t["power_law"] > t["empirical"]).groupby([t["noise"], t["ratio"]]).sum()
        print(summary.assign(power_law_wins=wins, of=t.groupby(["noise", "ratio"]).size()).to_string())
        doc["comparison"] = {
            "shrinkage": rho,
            "median_psnr_db": {f"{k[0]} {k[1]:.0%}": v for k, v in summary.to_dict("index").items()},
            "power_law_better": {f"{k[0]} {k[1]:.0%}": int(v) for k, v in wins.items()},
            "acquisitions_per_setting": int(len(TUNING) * 2),
        }
    ns.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {ns.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
