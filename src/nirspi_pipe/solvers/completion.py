"""Solver ``completion``: linear MMSE ("denoised completion") of the unmeasured Hadamard coefficients
from the measured ones, through a stationary image prior (the denoised completion of Lorente Mur,
Peyrin & Ducros, Opt. Express 2021, without its network; a single precomputed linear map like
Czajkowski et al.'s FDRI, Opt. Express 2018).

Model. The image ``x`` (``N = n²`` pixels, relative radiance) has mean ``μ`` (a flat image) and
covariance ``s·C``; the acquisition measures ``y = A x + w`` with ``A = H_M`` (the measured rows
``M`` of the 2D Hadamard matrix, in any scan order and at any ratio) and white noise ``w`` of
variance ``σ²`` per ±1 measurement. The linear MMSE estimate (Gauss–Markov) is::

    x̂ = μ + s C Aᵀ (s A C Aᵀ + σ² I)⁻¹ (y − A μ)

In the Hadamard domain (``Σ = H C H``, the coefficients' covariance) this is the issue's
``x̂_U = μ_U + Σ_UM (Σ_MM + D)⁻¹ (y − μ_M)`` for the unmeasured coefficients and
``x̂_M = μ_M + Σ_MM (Σ_MM + D)⁻¹ (y − μ_M)`` for the measured ones (denoised), ``D = σ²/s · I``,
followed by the inverse transform: the image-domain form is the same map with the inverse
transform folded in (``H⁻¹ Σ_{:,M} = C Aᵀ``). With ``σ = 0`` the measured coefficients are kept
exactly and only the unmeasured ones are estimated (regularised by ``EXACT_FLOOR``).

Prior (:class:`PowerLawPrior`): a stationary covariance whose power spectrum is
``S(f) = (f0² + |f|²)^(−α/2)``, ``f`` in cycles per image side, embedded in a ``2n × 2n`` torus
(so the ``n × n`` covariance is a principal block of a positive semi-definite circulant, hence
positive semi-definite), normalised to unit pixel variance. ``α`` and ``f0`` are fitted to a
training set that is disjoint from every benchmark image (``experiments/prior/build_prior.py``,
``experiments/prior/training.txt``; shipped as a few numbers in
``nirspi_pipe/data/completion_prior.json``, the ``N × N`` covariance is never stored). The
amplitude ``s`` is fitted to each acquisition by maximum marginal likelihood (type-II ML:
``y − Aμ ~ N(0, s Σ_MM + σ² I)``), so the prior needs no absolute brightness; with ``alpha: auto``
the exponent too is chosen per acquisition, by the same likelihood, among three shipped values (the
pooled fit and the 5th / 90th percentiles of the exponents fitted to each training crop alone).
``μ`` is the flat image at the measured mean (the DC reading / ``N``) when DC is measured, else at
the training set's mean.

Noise (``noise: auto``): ``σ`` from the split measurements themselves (the spread of the pair sums
``y⁺ + y⁻``, :func:`~nirspi_pipe.solvers.noise.estimate_noise`, rule ``pair_sums``), or the value a
source declares; a number fixes it (calibrated units of one ±1 measurement). The detector model's
parameters are not read: the solver sees only the acquisition, as it would from the device.

Guard (``guard: true``): the power law is a poor model of images that are sparse in the Walsh
basis (a checkerboard aligned with the patterns: completion lost 20 dB to zero-filling there). The
leave-one-out error of predicting each measured coefficient from the others, closed form for a
Gaussian model, is compared with that of the white prior (every coefficient independent: predicts
0); when the white prior predicts better, the solver returns its estimate, the zero-filled image
(Wiener-shrunk by ``sN/(sN + σ²)`` with noise).

Cost. Per (resolution, measured index set, prior) the solver caches the eigendecomposition
``Σ_MM = V Λ Vᵀ`` and ``V ∘ V`` (the guard), as float32: ``2m²·4`` bytes, 1.3 MiB at 64² and
10 %, 8 MiB at 25 %, 32 MiB at 50 %, 128 MiB at 100 % (three times that with ``alpha: auto``); in
process memory, least recently used first out beyond ``CACHE_BYTES`` (1 GiB; no files).
Building it costs ``m`` FFT convolutions and one eigendecomposition of ``Σ_MM`` (``O(m³)``).
Once cached a solve is, per prior, ``z = Vᵀ (y − Aμ)`` and the 1-D likelihood search for ``s``;
then, for the chosen one, ``k = V (z / (s λ + σ²))`` (``= K⁻¹(y − Aμ)``, also the guard's) and
``x̂ = μ + s · C Aᵀ k``: one inverse fast Hadamard transform and one FFT convolution. Two or
four ``m × m`` matrix-vector products, no iteration. (Until issue 36's last session the map
``G = C Aᵀ V``, ``N × m``, was cached and applied instead: the same image to float32 rounding, twice
the memory at 50 % and a slower build.)
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Annotated

import numpy as np
from scipy.optimize import minimize_scalar

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import fwht, is_power_of_two, sylvester
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.solvers.common import checked_coefficients, require_hadamard
from nirspi_pipe.solvers.crossval import holdout
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.solvers.noise import estimate_noise
from nirspi_pipe.types import Acquisition, Image2D

__all__ = [
    "PowerLawPrior",
    "CompletionSolver",
    "default_prior",
    "default_alphas",
    "completion_maps",
    "complete",
    "torus_convolve",
    "CACHE_BYTES",
    "EXACT_FLOOR",
    "PRIOR_FILE",
    "REFINE",
]

#: ``refine`` values: the linear estimate alone, or TV started from it.
REFINE = ("none", "tv")
#: The shipped prior (package data), written by ``experiments/prior/build_prior.py``.
PRIOR_FILE = "completion_prior.json"
#: In-memory cache budget of the completion maps, bytes (assumed: the three maps of ``alpha: auto``
#: for a full 64² acquisition, 3 × 128 MiB, must fit, or every solve would rebuild two of them).
CACHE_BYTES = 1024 * 2**20
#: With ``σ = 0`` the noise variance is floored at this fraction of ``s·λ_max`` (the largest
#: eigenvalue of ``s Σ_MM``): float64 eigenvalues below it are rounding, not signal.
EXACT_FLOOR = 1e-12
#: Patterns convolved with ``C`` per FFT batch (bounds the complex work array: 256 × (2n)² × 16 B,
#: 64 MiB at 64²).
_BATCH = 256


#: Roll-off frequencies ``f0`` a prior may have, cycles per image side. Assumed: the shipped fit
#: is 1.81 (experiments/completion); 1e-3 (a roll-off a thousandth of a cycle across the image)
#: and 1e3 (beyond the highest frequency of a 4096² image, 2048) bracket every prior a user can
#: mean. Outside, float64 failed (measured: f0 = 1e-300 made the spectrum 0^-α = inf at DC,
#: 1e300 overflowed f0²).
F0_RANGE = (1e-3, 1e3)


@dataclass(frozen=True)
class PowerLawPrior:
    """A stationary image covariance with power spectrum ``(f0² + |f|²)^(−α/2)``.

    Attributes:
        alpha: spectral exponent α (natural images: ≈ 2, Field 1987; van der Schaaf & van
            Hateren 1996).
        f0: roll-off frequency, cycles per image side (> 0; the variance of the image mean).
        mean: prior mean radiance (relative radiance), used when DC is not measured.
    """

    alpha: Annotated[float, Range(0.0, 6.0, "a spectral exponent")]
    f0: Annotated[float, Range(*F0_RANGE, "a roll-off frequency", note="cycles per image side")]
    mean: Annotated[float, Range(None, None, "a prior mean radiance")] = 0.0

    def __post_init__(self) -> None:
        check_ranges(self)

    @property
    def cache_key(self) -> tuple:
        """What identifies this prior's maps in the cache."""
        return ("power_law", float(self.alpha), float(self.f0))

    def spectrum(self, n: int) -> np.ndarray:
        """``(2n, 2n)`` spectrum on the embedding torus, frequencies in cycles per image side
        (``n`` pixels), unnormalised (the amplitude is fitted per acquisition)."""
        f = np.fft.fftfreq(2 * n) * n
        r2 = f[:, None] ** 2 + f[None, :] ** 2
        return (self.f0**2 + r2) ** (-0.5 * self.alpha)

    def covariance_apply(self, images: np.ndarray) -> np.ndarray:
        """``C x`` for a batch ``(B, n, n)``: zero-padded circular convolution on the ``2n`` torus
        (``O(B n² log n)``; the ``N × N`` matrix is never formed)."""
        return torus_convolve(images, _spectrum_cached(self.alpha, self.f0, images.shape[-1]))


def torus_convolve(images: np.ndarray, half_spectrum: np.ndarray) -> np.ndarray:
    """``C x`` for a batch ``(B, n, n)`` and a stationary covariance given by its spectrum on the
    ``2n × 2n`` torus (``half_spectrum``: the ``(2n, n + 1)`` half that ``rfft2`` uses): zero-padded
    circular convolution, in batches of ``_BATCH``."""
    n = images.shape[-1]
    out = np.empty(images.shape, dtype=np.float64)
    for start in range(0, images.shape[0], _BATCH):
        f = np.fft.rfft2(images[start : start + _BATCH], s=(2 * n, 2 * n))
        out[start : start + _BATCH] = np.fft.irfft2(f * half_spectrum, s=(2 * n, 2 * n))[:, :n, :n]
    return out


@lru_cache(maxsize=8)
def _spectrum_cached(alpha: float, f0: float, n: int) -> np.ndarray:
    spec = PowerLawPrior(alpha, f0).spectrum(n)
    spec = spec / spec.mean()  # covariance 1 at lag 0: the amplitude s is the pixel variance
    return np.ascontiguousarray(spec[:, : n + 1])  # the rfft2 half


@lru_cache(maxsize=1)
def _shipped() -> dict:
    text = resources.files("nirspi_pipe").joinpath("data").joinpath(PRIOR_FILE).read_text()
    return dict(json.loads(text)["prior"])


def default_prior() -> PowerLawPrior:
    """The shipped prior, the pooled fit (``nirspi_pipe/data/completion_prior.json``; its
    ``training`` key lists the images it was fitted to, ``experiments/prior/build_prior.py``
    rebuilds it)."""
    p = _shipped()
    return PowerLawPrior(alpha=float(p["alpha"]), f0=float(p["f0"]), mean=float(p["mean"]))


def default_alphas() -> tuple[float, ...]:
    """The shipped exponents among which ``alpha: auto`` chooses (ascending)."""
    return tuple(sorted(float(a) for a in _shipped()["alphas"]))


@dataclass(frozen=True)
class _Maps:
    """``lam`` ``(m,)`` eigenvalues of ``Σ_MM`` (ascending, float64), ``vt`` ``(m, m)`` = ``Vᵀ`` and
    ``v2`` ``(m, m)`` = ``V ∘ V`` (the guard's diagonal of ``K⁻¹``), float32."""

    lam: np.ndarray
    vt: np.ndarray
    v2: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.lam.nbytes + self.vt.nbytes + self.v2.nbytes)


class _ByteLRU:
    """A least-recently-used cache bounded by the total ``nbytes`` of its values."""

    def __init__(self, budget: int) -> None:
        self.budget = budget
        self.items: OrderedDict[tuple, _Maps] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: tuple) -> _Maps | None:
        with self.lock:
            hit = self.items.get(key)
            if hit is not None:
                self.items.move_to_end(key)
            return hit

    def put(self, key: tuple, value: _Maps) -> None:
        with self.lock:
            self.items[key] = value
            self.items.move_to_end(key)
            while len(self.items) > 1 and sum(v.nbytes for v in self.items.values()) > self.budget:
                self.items.popitem(last=False)

    def clear(self) -> None:
        with self.lock:
            self.items.clear()


_CACHE = _ByteLRU(CACHE_BYTES)


def _patterns(n: int, indices: np.ndarray) -> np.ndarray:
    """``(m, n, n)`` the ±1 patterns ``h_i h_jᵀ`` of the flat indices (the rows of ``A``)."""
    h = sylvester(n)
    i, j = indices // n, indices % n
    return h[i][:, :, None] * h[j][:, None, :]


def completion_maps(n: int, indices: np.ndarray, prior: PowerLawPrior) -> _Maps:
    """The cached maps of one (resolution, measured set, prior) (module doc: cost and size).

    ``prior`` needs ``covariance_apply`` (``(B, n, n) ↦ C x``), ``cache_key`` and ``mean``: any
    covariance can be plugged in (``experiments/prior/build_prior.py`` compares an empirical one)."""
    idx = np.asarray(indices, dtype=np.int64)
    key = (int(n), idx.tobytes(), prior.cache_key)
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    size = n * n
    cp = prior.covariance_apply(_patterns(n, idx)).reshape(idx.size, size)  # rows: C aₖ
    sigma_mm = fwht(cp, axis=-1)[:, idx]  # A C Aᵀ (symmetric)
    sigma_mm = 0.5 * (sigma_mm + sigma_mm.T)
    lam, v = np.linalg.eigh(sigma_mm)
    lam = np.maximum(lam, 0.0)
    v32 = v.astype(np.float32)
    maps = _Maps(lam=lam, vt=np.ascontiguousarray(v32.T), v2=v32 * v32)
    _CACHE.put(key, maps)
    return maps


def _fit_scale(z2: np.ndarray, lam: np.ndarray, sigma2: float) -> float:
    """Type-II maximum likelihood of the prior's amplitude ``s``: ``zᵢ ~ N(0, s λᵢ + σ²)``
    (closed form when ``σ = 0``; else scipy's bounded Brent search on ``ln s``)."""
    live = lam > EXACT_FLOOR * float(lam[-1])
    z2, lam = z2[live], lam[live]
    if sigma2 <= 0:  # closed form
        return float(np.mean(z2 / lam))
    guess = max(float(np.mean(np.maximum(z2 - sigma2, 0.0) / lam)), 1e-30)

    def nll(log_s: float) -> float:
        v = np.exp(log_s) * lam + sigma2
        return float(np.sum(np.log(v) + z2 / v))

    lo, hi = np.log(guess) - 12.0, np.log(guess) + 6.0
    res = minimize_scalar(nll, bounds=(lo, hi), method="bounded", options={"xatol": 0.02})
    return float(np.exp(res.x))


@dataclass(frozen=True)
class _Fit:
    """One prior fitted to one acquisition: maps, ``z = Vᵀ(y − Aμ)``, amplitude, noise variance
    used, and the negative log marginal likelihood per measurement (up to ½ ln 2π)."""

    maps: _Maps
    z: np.ndarray
    scale: float
    noise2: float
    nll: float


def _fit(maps: _Maps, r: np.ndarray, sigma: float, scale: float | None) -> _Fit:
    z = (maps.vt @ r.astype(np.float32)).astype(np.float64)
    s = _fit_scale(z * z, maps.lam, sigma**2) if scale is None else float(scale)
    lam_max = float(maps.lam[-1]) if maps.lam.size else 0.0
    noise2 = max(sigma**2, EXACT_FLOOR * s * lam_max)
    denom = s * maps.lam + noise2
    live = denom > 0
    nll = 0.5 * float(np.sum(np.log(denom[live]) + z[live] ** 2 / denom[live])) / max(int(live.sum()), 1)
    return _Fit(maps, z, s, noise2, nll)


def complete(
    n: int,
    indices: np.ndarray,
    y: np.ndarray,
    sigma: float,
    prior: PowerLawPrior | Sequence[PowerLawPrior],
    scale: float | None = None,
    guard: bool = False,
) -> tuple[np.ndarray, dict[str, float]]:
    """The linear MMSE image ``(n, n)`` from measurements ``y`` (calibrated ±1 coefficients at
    flat ``indices``) with noise ``sigma`` per measurement, and bookkeeping (module doc).

    ``prior``: one prior, or several (then the one of highest marginal likelihood of ``y`` is used,
    ``info["alpha"]``); ``scale``: the prior's amplitude ``s`` (None: fitted by marginal likelihood).
    ``guard``: fall back to the white prior when it predicts the measurements better by
    leave-one-out (:func:`_loo_ratio`, module doc)."""
    priors = list(prior) if isinstance(prior, Sequence) else [prior]
    size = n * n
    r = np.asarray(y, dtype=np.float64).copy()
    dc = np.flatnonzero(np.asarray(indices) == 0)
    mu = float(r[dc[0]]) / size if dc.size else float(priors[0].mean)
    if dc.size:
        r[dc[0]] -= mu * size  # A μ: a flat image has only a DC coefficient
    fits = [_fit(completion_maps(n, indices, p), r, sigma, scale) for p in priors]
    best = int(np.argmin([f.nll for f in fits]))
    f = fits[best]
    denom = f.scale * f.maps.lam + f.noise2
    safe = np.where(denom > 0, denom, 1.0)
    q = np.where(denom > 0, f.z / safe, 0.0)
    k_r = (f.maps.vt.T @ q.astype(np.float32)).astype(np.float64)  # K⁻¹ (y − Aμ)
    info: dict[str, float] = {}
    if guard:
        live = np.ones(r.size, dtype=bool)
        live[dc] = False
        info["loo_ratio"] = ratio = _loo_ratio(f, safe, live, r, k_r)
        if ratio > 1.0:  # the white prior predicts the measurements better: zero-filled, shrunk
            s0 = max(float(np.mean(r[live] ** 2)) - sigma**2, 0.0) / size if live.any() else 0.0
            gain = s0 * size / (s0 * size + sigma**2) if s0 * size + sigma**2 > 0 else 1.0
            shrunk = r * gain
            shrunk[dc] = r[dc]
            # no neg_log_evidence: no prior was fitted (a NaN would be left out of the record anyway)
            info.update(alpha=0.0, prior_scale=s0, noise_sigma=float(sigma), prior_mean=mu)
            return mu + zero_filled_inverse(n, indices, shrunk), info
    back = np.zeros(size)
    back[np.asarray(indices, dtype=np.int64)] = f.scale * k_r
    image = mu + priors[best].covariance_apply(fwht(back).reshape(1, n, n))[0]  # μ + s C Aᵀ K⁻¹(y − Aμ)
    info |= {
        "alpha": float(getattr(priors[best], "alpha", np.nan)),
        "prior_scale": f.scale,
        "noise_sigma": float(sigma),
        "prior_mean": mu,
        "neg_log_evidence": f.nll,
    }
    return image.reshape(n, n), info


def _loo_ratio(f: _Fit, denom: np.ndarray, live: np.ndarray, r: np.ndarray, k_r: np.ndarray) -> float:
    """Leave-one-out prediction error of the measured coefficients under the fitted prior, over
    that of the white prior (which predicts every left-out coefficient as 0), DC excluded.

    For a Gaussian model ``r ~ N(0, K)`` the residual of predicting ``rᵢ`` from the others is
    ``(K⁻¹r)ᵢ / (K⁻¹)ᵢᵢ`` (Sundararajan & Keerthi, Neural Comput. 13, 2001; Rasmussen & Williams
    2006, Eq. 5.12), here with ``K⁻¹ = V diag(1/(sλ + σ²)) Vᵀ``: ``k_r = K⁻¹r`` (computed once for
    the image too) and the diagonal, one more ``m × m`` product."""
    if not live.any():
        return 0.0
    inv = (1.0 / denom).astype(np.float32)
    k_ii = (f.maps.v2 @ inv).astype(np.float64)
    loo = k_r[live] / k_ii[live]
    white = float(np.sum(r[live] ** 2))
    return float(np.sum(loo**2)) / white if white > 0 else 0.0


#: Largest ``noise`` (σ per measurement, in the coefficients' units). Assumed: the solver keeps
#: ``1/(sλ + σ²)`` in float32 for its maps, which underflows to 0 once σ² nears 1e38 (measured:
#: σ = 1e100 gave 0/0 in the leave-one-out guard, 1e300 overflowed σ² itself); 1e12 is 1e5 times
#: the largest coefficient a relative image gives (|y| <= n² <= 4096² = 1.7e7) and measured to
#: finish, so every σ a user can mean is below it.
NOISE_MAX = 1e12


@dataclass(frozen=True)
class CompletionSolver:
    """Solver ``completion``: linear MMSE completion and denoising of Hadamard coefficients under a
    stationary power-law image prior (module doc; Lorente Mur et al. 2021).

    Attributes:
        noise: ``auto`` (σ from the acquisition: declared, or the split pairs' sums,
            :func:`~nirspi_pipe.solvers.noise.estimate_noise`), or σ ≥ 0 per ±1 measurement in
            calibrated units (relative radiance × pixels); 0 treats the data as exact.
        alpha: spectral exponent of the prior; ``auto``: of the shipped exponents (the training
            crops' 5th percentile, the pooled fit and the 90th percentile,
            ``nirspi_pipe/data/completion_prior.json``), the one under which the measurements are
            most likely (marginal likelihood; three maps cached instead of one).
        f0: roll-off frequency of the prior, cycles per image side; null: the shipped one.
        guard: when the white prior (no correlation between coefficients: the zero-filled image,
            Wiener-shrunk with noise) predicts each measured coefficient from the others better than
            the fitted prior does (leave-one-out, DC excluded; ``info.loo_ratio`` > 1), return
            that instead (``info.alpha`` = 0). Images that are sparse in the Walsh basis (a
            checkerboard aligned with the patterns) are where the power law is wrong.
        refine: ``none`` (the linear estimate), or ``tv``: ``fista_tv`` at its defaults (hold-out
            cross-validated weight, :class:`~nirspi_pipe.solvers.fista_tv.FistaTVSolver`) started
            from the completion estimate: each training fit of the weight's cross-validation from
            the completion of its own training measurements (under the prior the full data chose,
            or zero-filled when the guard fired), the final fit from the completion of all of them.
            λ = 0 is then the completion with the measured coefficients set to the data. About one
            ``fista_tv`` solve plus a second map (the training set's) per acquisition.
    """

    noise: Annotated[float | str, Range(0.0, NOISE_MAX, "a noise sigma per measurement", also=("auto",))] = "auto"
    alpha: Annotated[float | str, Range(0.0, 6.0, "a spectral exponent", also=("auto",))] = "auto"
    f0: Annotated[float | None, Range(*F0_RANGE, "a roll-off frequency", note="cycles per image side")] = None
    guard: bool = True
    refine: Annotated[str, OneOf(REFINE)] = "none"

    def __post_init__(self) -> None:
        check_ranges(self)

    def priors(self) -> list[PowerLawPrior]:
        """The priors in use: the shipped exponents (``alpha: auto``) or the one given, with the
        shipped ``f0`` unless ``f0`` is set."""
        base = default_prior()
        f0 = base.f0 if self.f0 is None else float(self.f0)
        alphas = default_alphas() if isinstance(self.alpha, str) else (float(self.alpha),)
        return [PowerLawPrior(alpha=a, f0=f0, mean=base.mean) for a in alphas]

    def solve(self, acquisition: Acquisition) -> Image2D:
        require_hadamard(acquisition, "completion")
        n = acquisition.n
        if not is_power_of_two(n):
            raise ConfigError("camera.resolution", n, "a power of two (Hadamard patterns)", absolute=True)
        y = checked_coefficients(acquisition, "completion")
        info: dict[str, object] = {"iterations": 1, "stop_reason": "direct"}
        if isinstance(self.noise, str):
            est = estimate_noise(acquisition)
            sigma, info["noise_method"] = float(est.sigma), est.method
        else:
            sigma, info["noise_method"] = float(self.noise), "fixed"
        idx = np.asarray(acquisition.indices, dtype=np.int64)
        priors = self.priors()
        image, extra = complete(n, idx, y, sigma, priors, guard=bool(self.guard))
        info.update(extra)
        if self.refine == "none":
            return Image2D(image, info=info)
        fired = bool(self.guard) and float(extra.get("loo_ratio", 0.0)) > 1.0
        chosen = [] if fired else [p for p in priors if p.alpha == extra["alpha"]]

        def complete_on(data: np.ndarray, rows: np.ndarray) -> np.ndarray:
            """The completion of ``data[rows]`` alone (zero-filled when the guard fired)."""
            if not chosen:  # zero-filled on the training rows: fista_tv's own start
                return zero_filled_inverse(n, idx[rows], data[rows])
            return complete(n, idx[rows], data[rows], sigma, chosen)[0]

        def start(rows: np.ndarray | None) -> np.ndarray:
            return image if rows is None else complete_on(y, rows)

        tv = FistaTVSolver().solve(acquisition, start=start)
        record = {**tv.info, **{f"completion_{k}": v for k, v in info.items()}}
        if tv.info.get("lam_rule") == "cv":
            record["cv_score_completion"] = own = _holdout_score(n, idx, y, sigma, complete_on)
            if own <= float(tv.info["cv_score"]):  # the completion itself predicts better than any TV
                return Image2D(image, info={**record, "refine_chosen": "completion"})
        return Image2D(tv.data, info={**record, "refine_chosen": "tv"})


def _holdout_score(n: int, idx: np.ndarray, y: np.ndarray, sigma: float, complete_on) -> float:
    """The completion's own score under ``fista_tv``'s cross-validation
    (:func:`~nirspi_pipe.solvers.crossval.cv_weight`, the same held-out set, Stein correction and
    Monte-Carlo probe): an estimate of its image's mean squared error, comparable with ``fista_tv``'s
    ``cv_score`` (the chosen weight's). ``complete_on(data, rows)`` is the completion of
    ``data[rows]``."""
    size = n * n
    train, held = holdout(y)
    if held.size == 0:
        train, held = holdout(np.ones(y.size))

    def predict(image: np.ndarray, rows: np.ndarray) -> np.ndarray:
        return fwht(image.ravel())[idx[rows]]

    x = complete_on(y, train)
    y_t = y[train]
    fitted_t = predict(x, train)
    res_t = float(np.sum((fitted_t - y_t) ** 2))
    if sigma > 0:  # Stein's correction, the divergence by one probe (as cv_weight)
        probe = np.random.default_rng(0).standard_normal(y_t.size)
        eps = 0.01 * sigma
        shifted = y.copy()
        shifted[train] = y_t + eps * probe
        x1 = complete_on(shifted, train)
        div = float((predict(x1, train) - fitted_t) @ probe / eps)
        res_t += -train.size * sigma**2 + 2.0 * sigma**2 * div
    err_h = float(np.sum((predict(x, held) - y[held]) ** 2)) - held.size * sigma**2
    return res_t / float(size) ** 2 + err_h * (size - y.size) / held.size / float(size) ** 2


def clear_cache() -> None:
    """Empty the in-memory map cache (tests, benchmarks)."""
    _CACHE.clear()
