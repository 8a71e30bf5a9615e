"""Image and depth metrics.

SSIM and PSNR come from scikit-image; RMSE is the paper's Eq. (16). Images are relative
radiance in [0, 1], so ``data_range = 1``.

Two scores per image metric (docs/paper.md, "Metrics"):

* ``psnr``, ``ssim`` — **normalised**, as the single-pixel-imaging literature reports them: the
  reference is the noise-free image of the same camera in the same condition
  (``Acquisition.reference``: fall-off, fog transmission and veil included; the truth's radiance
  when a source gives none), scaled so that its peak is 1; the reconstruction is mapped onto it
  by the least-squares gain and offset (:func:`fit_gain_offset`), then scored with data range 1.
  A noise-free reconstruction scores at least 100 dB in every condition (fog included); PSNR is
  capped at :data:`PSNR_CAP_DB` so that records stay finite. They are given only where the data
  say they mean something (:func:`content_test`: the fitted gain is distinguishable from zero at
  5σ); otherwise they are left out and flagged (``degenerate_reference`` or ``degenerate_image``,
  with the reason in a warning), at every resolution (docs/paper.md, "Metrics").
* ``psnr_raw``, ``ssim_raw`` — **radiometric**: the raw reconstruction against the clear-air
  radiance, data range 1 (the gain of clear air at the nominal distance is kept, so fog and
  fall-off count as errors).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import fwht, is_power_of_two
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.stages import Products

__all__ = [
    "CONTENT_LEVEL",
    "CONTENT_T",
    "DEGENERATE_FLAG",
    "NO_CONTENT_FLAG",
    "Content",
    "content_test",
    "measured_values",
    "measured_view",
    "PSNR_CAP_DB",
    "ImageMetrics",
    "degenerate_reference",
    "fit_gain_offset",
    "normalised_pair",
    "psnr",
    "rmse",
    "ssim",
]

_IMAGE_METRICS = ("ssim", "psnr", "rmse")

#: Normalised PSNR is capped here (dB): float64 rounding of a noise-free fit lies far above it,
#: and an infinite value would not survive the records' no-NaN/no-inf rule.
PSNR_CAP_DB = 200.0

#: One-sided level of the content test (:func:`content_test`): 5σ of a normal, p = 2.87e-7, the
#: particle physicists' "discovery" convention (Particle Data Group, Review of Particle Physics,
#: chapter "Statistics", significance tests: Z = 5 for a discovery). Chosen so strict because
#: the test also guards the claim that an image without content never gets a score: an image
#: independent of the reference passes with probability at most 2.87e-7
#: (tests/test_scores_degenerate.py checks the statistic's calibration on noise images).
CONTENT_LEVEL = 2.866515719235352e-7
#: The flag a degenerate reference leaves in the metrics (1.0) instead of ``psnr``/``ssim``.
DEGENERATE_FLAG = "degenerate_reference"
#: The flag an image without detectable content leaves (1.0) instead of ``psnr``/``ssim``.
NO_CONTENT_FLAG = "degenerate_image"
#: Beside :data:`NO_CONTENT_FLAG` when the test ran: its t statistic of the fitted gain.
CONTENT_T = "content_t"


def degenerate_reference(reference: np.ndarray) -> str | None:
    """Why no gain-and-offset fit to ``reference`` can be scored, whatever the image (one phrase),
    or None: empty or not finite, no positive peak to scale to 1, or the same value everywhere (in
    float64: nothing for a gain to map onto)."""
    ref = np.asarray(reference, dtype=np.float64)
    if ref.size == 0 or not np.all(np.isfinite(ref)):
        return "the reference image is empty or not finite"
    peak, low = float(ref.max()), float(ref.min())
    if not peak > 0:
        return f"the reference image is dark (peak {peak:.3g} of a white target; nothing of the object arrives)"
    if not peak > low:
        return "the reference image is uniform (the same value in every pixel; no object is visible)"
    return None


@dataclass(frozen=True)
class Content:
    """Outcome of :func:`content_test`. ``reason`` is None when the normalised scores mean
    something; ``flag`` is the metrics key that marks why not; ``t``/``dof`` the test's statistic
    and degrees of freedom (NaN when it did not run)."""

    reason: str | None
    flag: str | None = None
    t: float = float("nan")
    dof: int = 0


def content_test(
    reference: np.ndarray,
    estimate: np.ndarray,
    independent: int | None = None,
    seen: np.ndarray | None = None,
    gain_test: bool = True,
) -> Content:
    """Whether ``estimate`` shows ``reference`` well enough for the gain-and-offset-fitted scores.

    The fit regresses the reference on the image, ``reference = a·estimate + b + e``. The scores
    mean something only where the gain ``a`` is distinguishable from zero: the one-sided t-test of
    the regression slope (H0: ``a ≤ 0``; ``t = r·√ν / √(1 − r²)`` with ``r`` the sample correlation
    and ``ν = n − 2`` degrees of freedom, Student's t; the textbook test of a regression slope,
    e.g. Draper & Smith, *Applied Regression Analysis*, chapter 1) at level :data:`CONTENT_LEVEL`. Otherwise
    the fit only returns ``mean(reference)`` plus a chance fraction of its contrast, and PSNR/SSIM
    would measure how flat the reference is, not the image (issue 40). One-sided: an image that
    is the reference's negative is not a picture of it.

    ``independent`` is how many independent values the image carries (default: its pixels): an
    image reconstructed out of fewer values has ``n`` = that many (a compressed acquisition: its
    distinct measured patterns, :func:`measured_values`). ``seen``,
    when given, is the part of the reference those values can show (:func:`measured_view`: the
    reference projected onto the measured patterns); the image is then tested against it and
    against the reference, each at half the level (Bonferroni): a zero-filled reconstruction
    shows what its measurements see, a solver that fills in the rest (OMP, the completion) may
    show more of the reference (under H0 the image is independent of the reference, so each test
    holds for any fixed target).
    ``gain_test=False`` skips the t-test (the other checks stay): for an image computed from one
    that passed it (an upscaled image from the camera's: under H0 both are independent of the
    scene, so the camera's test is the test of both).

    Not scored, with the reason: a reference without a fit (:func:`degenerate_reference`;
    ``degenerate_reference``), an image that is not finite or is the same value everywhere (a
    constant has no content; ``degenerate_image``), fewer than 3 independent values, or a gain
    that the test does not tell from zero (``degenerate_image``, its ``t`` kept).
    """
    why = degenerate_reference(reference)
    if why is not None:
        return Content(why, DEGENERATE_FLAG)
    y = np.asarray(reference, dtype=np.float64).ravel()
    view = None if seen is None else np.asarray(seen, dtype=np.float64).ravel()
    x = np.asarray(estimate, dtype=np.float64).ravel()
    if not np.all(np.isfinite(x)):
        return Content("the image is not finite", NO_CONTENT_FLAG)
    if not float(x.max()) > float(x.min()):
        return Content("the image is the same value everywhere: it has no content to score", NO_CONTENT_FLAG)
    if not gain_test:
        return Content(None)
    n = x.size if independent is None else min(int(independent), x.size)
    dof = n - 2
    if dof < 1:
        return Content(
            f"the image carries {n} independent value(s); a gain needs at least 3 to be tested", NO_CONTENT_FLAG
        )
    # the correlation from scaled, centred copies: no overflow for images near the float64 limits
    xc = x / float(np.max(np.abs(x)))
    xc = xc - xc.mean()
    sxx = float(xc @ xc)
    if not sxx > 0:
        return Content("the image is the same value everywhere: it has no content to score", NO_CONTENT_FLAG)
    from scipy.special import stdtr  # start-up: loads scipy.special (already loaded by skimage.metrics)

    tests = []  # (p, t) against each target
    for target in (y,) if view is None else (y, view):
        ymax = float(np.max(np.abs(target))) if np.all(np.isfinite(target)) else 0.0
        yc = target / ymax if ymax > 0 else np.zeros_like(target)
        yc = yc - yc.mean()
        syy = float(yc @ yc)
        if not syy > 0:
            continue
        r = float(np.clip((xc @ yc) / np.sqrt(sxx * syy), -1.0, 1.0))
        t = math.copysign(math.inf, r) if abs(r) >= 1.0 else r * math.sqrt(dof) / math.sqrt(1.0 - r * r)
        tests.append((float(stdtr(dof, -t)), t))  # one-sided: P(T >= t) under H0; 1 at t = -inf, 0 at +inf
    if not tests:
        return Content("its measurements see none of the reference's contrast (only the mean)", NO_CONTENT_FLAG)
    p, t = min(tests)
    p = min(1.0, p * len(tests))  # Bonferroni over the targets tested
    if not p < CONTENT_LEVEL:
        return Content(
            f"the image shows no detectable trace of the reference (fitted gain's t = {t:.2f} on {dof} degrees of "
            f"freedom, one-sided p = {p:.2g} ≥ {CONTENT_LEVEL:.2g}, 5σ)",
            NO_CONTENT_FLAG,
            t,
            dof,
        )
    return Content(None, None, t, dof)


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root-mean-square error over all ``M × N`` entries, Eq. (16). Units of the inputs."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def psnr(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (scikit-image); ``inf`` for an exact reconstruction."""
    # start-up: loads scipy, skimage, charset_normalizer (250 ms here)
    from skimage.metrics import (
        peak_signal_noise_ratio,
    )

    if rmse(truth, estimate) == 0.0:
        return float("inf")
    return float(peak_signal_noise_ratio(truth, estimate, data_range=data_range))


def ssim(truth: np.ndarray, estimate: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (scikit-image, 7×7 Gaussian-free window; smaller for tiny images)."""
    side = min(truth.shape)
    win = min(7, side if side % 2 == 1 else side - 1)
    if win < 3:
        return float("nan")
    if _float64_pair(truth, estimate):
        value = _ssim_float64(truth, estimate, float(data_range), win)
    else:
        # start-up: loads scipy, skimage, charset_normalizer (250 ms here)
        from skimage.metrics import (
            structural_similarity,
        )

        value = float(structural_similarity(truth, estimate, data_range=data_range, win_size=win))
    # SSIM lies in [-1, 1] (Wang et al. 2004, Eq. 13: a product of terms of modulus <= 1); float64
    # rounding put a noise-free 8² image of a board at 1 km at 1 + 2.4e-13 (issue 40)
    return float(np.clip(value, -1.0, 1.0)) if np.isfinite(value) else value


def _float64_pair(a: Any, b: Any) -> bool:
    return (
        isinstance(a, np.ndarray)
        and isinstance(b, np.ndarray)
        and a.dtype == np.float64
        and b.dtype == np.float64
        and a.ndim == 2
        and a.shape == b.shape
    )


def _ssim_float64(im1: np.ndarray, im2: np.ndarray, data_range: float, win: int) -> float:
    """scikit-image's ``structural_similarity(im1, im2, data_range=..., win_size=win)`` (0.26,
    uniform window, sample covariance, K1 = 0.01, K2 = 0.03) for two float64 images of one shape:
    its operations in its order, so the same bits (tests/test_metrics_wiring.py compares), with the
    five window means in one filter call on the stacked images (a 1-tap axis is not filtered; each
    line is filtered alone) instead of five calls and skimage's argument checks: 0.35 -> 0.19 ms
    a call at 32², 6-7 calls per metrics stage."""
    # start-up: loads scipy.ndimage (already loaded by skimage.metrics, which the stage warms up)
    from scipy.ndimage import uniform_filter

    if np.any((np.asarray(im1.shape) - win) < 0) or win % 2 != 1:
        raise ValueError(f"SSIM window {win} does not fit an image of shape {im1.shape}")
    means = uniform_filter(np.stack([im1, im2, im1 * im1, im2 * im2, im1 * im2]), size=(1, win, win))
    ux, uy, uxx, uyy, uxy = means
    np_ = win**2
    cov_norm = np_ / (np_ - 1)
    vx = cov_norm * (uxx - ux * ux)
    vy = cov_norm * (uyy - uy * uy)
    vxy = cov_norm * (uxy - ux * uy)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    a1, a2, b1, b2 = (2 * ux * uy + c1, 2 * vxy + c2, ux**2 + uy**2 + c1, vx + vy + c2)
    d = b1 * b2
    s = (a1 * a2) / d
    pad = (win - 1) // 2
    crop = s[pad : s.shape[0] - pad, pad : s.shape[1] - pad]
    return float(crop.mean(dtype=np.float64))


def fit_gain_offset(reference: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """Least-squares gain ``a`` and offset ``b`` minimising ``‖a·estimate + b − reference‖²``.

    A constant estimate gets ``a = 0`` and ``b = mean(reference)``. Dimensionless gain; offset
    in the reference's units."""
    x = np.asarray(estimate, dtype=np.float64).ravel()
    y = np.asarray(reference, dtype=np.float64).ravel()
    # fitted on the estimate scaled to a peak magnitude of 1: no overflow of the sums of squares
    # for an image near the float64 limits (a reconstruction of ±3e300, issue 40)
    scale = float(np.max(np.abs(x))) if x.size and np.all(np.isfinite(x)) else 0.0
    if not scale > 0:
        return 0.0, float(y.mean())
    xs = x / scale
    xc = xs - xs.mean()
    var = float(xc @ xc)
    if not var > 0:
        return 0.0, float(y.mean())
    a = float(xc @ (y - y.mean())) / var
    return a / scale, float(y.mean() - a * xs.mean())


def normalised_pair(reference: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference scaled to peak 1 and the estimate mapped onto it by :func:`fit_gain_offset`.
    A reference without a positive peak is left unscaled."""
    ref = np.asarray(reference, dtype=np.float64)
    peak = float(np.max(ref)) if ref.size else 0.0
    if peak > 0:
        ref = ref / peak
    est = np.asarray(estimate, dtype=np.float64)
    a, b = fit_gain_offset(ref, est)
    scale = float(np.max(np.abs(est))) if est.size and np.all(np.isfinite(est)) else 0.0
    if not scale > 0:
        return ref, np.full_like(est, b)
    return ref, (a * scale) * (est / scale) + b


def _psnr_normalised(ref: np.ndarray, est: np.ndarray) -> float:
    err = rmse(ref, est)
    if err == 0.0:
        return PSNR_CAP_DB
    return float(min(PSNR_CAP_DB, -20.0 * np.log10(err)))


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics ``default``: SSIM, PSNR (dB) and RMSE of the 2D reconstruction (module docstring):
    ``ssim``/``psnr`` normalised, ``ssim_raw``/``psnr_raw`` radiometric, ``rmse`` (Eq. 16) raw
    against the ground-truth radiance (relative, data range 1).

    Attributes:
        names: which of ``ssim``, ``psnr``, ``rmse`` to compute.
        clip: clip the reconstruction to [0, 1] before the raw scores (a physical image cannot
            leave it).
    """

    names: tuple[str, ...] = field(default=_IMAGE_METRICS)
    clip: bool = False

    def __post_init__(self) -> None:
        bad = [n for n in self.names if n not in _IMAGE_METRICS]
        if bad:
            raise ConfigError("names", list(self.names), f"a subset of {list(_IMAGE_METRICS)}")
        # scikit-image's metric functions bring scipy.stats, 0.7 s (python -X importtime -c "from
        # skimage.metrics import structural_similarity"): loaded when a metrics stage is built, so
        # that composing a config (which imports this module for its defaults) does not pay it and
        # the first job's timed metrics stage does not either
        self.warm_up({})

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Import scikit-image's metric functions (0.7 s with scipy.stats;
        :class:`nirspi_pipe.stages.WarmsUp`)."""
        # warm-up: loads scipy, skimage, charset_normalizer (250 ms here), before jobs fork
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity  # noqa: F401

    def compute(self, products: Products) -> dict[str, float]:
        if products.truth is None:
            warnings.warn("metrics: no ground truth in this acquisition; nothing to score", stacklevel=2)
            return {}
        return self.camera_scores(products)[0]

    def camera_scores(self, products: Products) -> tuple[dict[str, float], Content]:
        """The scores of the camera's image (:meth:`compute`; ``products.truth`` given) and the
        :func:`content_test` of it against the camera's noise-free reference (run whatever
        ``names``: an upscaled image's scores take it as their ``upstream``)."""
        truth, acq = products.truth, products.acquisition
        assert truth is not None
        est = np.asarray(products.image.data, dtype=np.float64)
        ref = np.asarray(truth.radiance if acq.reference is None else acq.reference, dtype=np.float64)
        content = None
        if est.shape == ref.shape == np.shape(truth.radiance):  # else score() says which shapes differ
            content = content_test(ref, est, measured_values(acq, est.size), measured_view(acq, ref))
        out = self.score(truth.radiance, est, acq.reference, content=content)
        assert content is not None
        return out, content

    def score(
        self,
        truth: np.ndarray,
        estimate: np.ndarray,
        reference: np.ndarray | None = None,
        prefix: str = "",
        independent: int | None = None,
        upstream: str | None = None,
        seen: np.ndarray | None = None,
        content: Content | None = None,
        raw: bool = True,
    ) -> dict[str, float]:
        """The scores of ``estimate`` against ``truth`` (raw) and ``reference`` (normalised; the
        truth when None), keys prefixed by ``prefix``. The normalised ones only where
        :func:`content_test` (given ``independent`` and ``seen``) says they mean something; otherwise its flag
        (1.0, and ``content_t`` when the test ran) and a warning with the reason. ``upstream``: for an image
        computed from another (the camera's, for an upscaled image), that one's flag when it has no
        content (then this one has none either: post-processing adds no information about the
        scene), or ``""`` when it passed (then only this image's own constant/finite checks run,
        not a second t-test). ``content``: the :func:`content_test` of these very arguments,
        when the caller has run it already. ``raw=False`` leaves out ``psnr_raw`` and ``ssim_raw``."""
        est = np.asarray(estimate, dtype=np.float64)
        ref = np.asarray(truth, dtype=np.float64)
        if est.shape != ref.shape:
            raise ValueError(f"reconstruction {est.shape} and ground truth {ref.shape} differ in shape")
        norm_ref = ref if reference is None else np.asarray(reference, dtype=np.float64)
        if norm_ref.shape != est.shape:
            raise ValueError(f"reconstruction {est.shape} and reference {norm_ref.shape} differ in shape")
        if not {"psnr", "ssim"} & set(self.names):
            content = Content(None)
        elif upstream and degenerate_reference(norm_ref) is None:
            content = Content(
                f"it is computed from the camera's image, which has no content to score ({upstream})", NO_CONTENT_FLAG
            )
        elif content is None:
            content = content_test(norm_ref, est, independent, seen, gain_test=upstream is None)
        why = content.reason
        if why is not None:
            warnings.warn(
                f"metrics: {why}, so the normalised {prefix}psnr/{prefix}ssim are undefined and left out "
                f"({prefix}{content.flag}=1); the raw scores ({prefix}psnr_raw, {prefix}ssim_raw, {prefix}rmse) are kept",
                stacklevel=2,
            )
        raw_est = np.clip(est, 0.0, 1.0) if self.clip else est
        out: dict[str, float] = {}
        nref, nest = normalised_pair(norm_ref, est) if why is None else (norm_ref, est)
        for name in self.names:
            if name == "rmse":
                out[f"{prefix}rmse"] = rmse(ref, raw_est)
            elif name == "psnr":
                if why is None:
                    out[f"{prefix}psnr"] = _psnr_normalised(nref, nest)
                if raw:
                    out[f"{prefix}psnr_raw"] = psnr(ref, raw_est)
            else:
                if why is None:
                    out[f"{prefix}ssim"] = ssim(nref, nest)
                if raw:
                    out[f"{prefix}ssim_raw"] = ssim(ref, raw_est)
        if content.flag is not None:
            out[f"{prefix}{content.flag}"] = 1.0
            if np.isfinite(content.t):
                out[f"{prefix}{CONTENT_T}"] = content.t
        return out


def measured_view(acquisition: Any, reference: np.ndarray) -> np.ndarray | None:
    """The part of ``reference`` that the acquisition's Hadamard patterns see: its projection
    onto the measured patterns (the zero-filled inverse of its measured coefficients,
    :func:`nirspi_pipe.solvers.fwht.zero_filled_inverse`). None when every pattern was measured
    (then it is the reference), for explicit pattern matrices, or when the shapes differ."""
    ref = np.asarray(reference, dtype=np.float64)
    n = int(getattr(acquisition, "n", 0) or 0)
    indices = getattr(acquisition, "indices", None)
    if indices is None or getattr(acquisition, "patterns", None) is not None or not is_power_of_two(n):
        return None
    if ref.shape != (n, n) or not np.all(np.isfinite(ref)):
        return None
    measured = np.unique(np.asarray(indices, dtype=np.int64))
    if measured.size >= n * n or measured.size == 0 or measured.min() < 0 or measured.max() >= n * n:
        return None
    return zero_filled_inverse(n, measured, fwht(ref.ravel())[measured])


def measured_values(acquisition: Any, pixels: int) -> int:
    """How many independent values an image reconstructed from ``acquisition`` carries: its
    pixels, or fewer distinct measured patterns (a compressed acquisition spans no more)."""
    indices = getattr(acquisition, "indices", None)
    if indices is None or getattr(acquisition, "patterns", None) is not None:
        m = len(getattr(acquisition, "y_pos", ())) or pixels
    else:
        m = int(np.unique(np.asarray(indices)).size)
    return int(min(pixels, m)) if m > 0 else pixels
