"""The forward model as a chain of physical effects (paper §§3–5, Eqs. 5–12).

The simulator (:class:`nirspi_pipe.sources.simulator.Simulator`) is an ordered tuple of effects;
:func:`forward_model` builds the chain that the config groups ``fog``, ``illumination`` and
``detector`` enable. An effect that is off is not in the chain, so it costs nothing.

The effect interface
--------------------
An effect is any object with

* ``name: str`` — listed, in chain order, in the record (``info.source.effects``);
* ``apply(signal: Signal, exposure: Exposure) -> Signal`` — one pure step;

and optionally ``domain`` (``"image"``, ``"readings"`` (default) or ``"output"``: where
:func:`forward_model` places an extra effect), ``streams: tuple[int, ...]`` (the random streams
it draws from, :meth:`Exposure.rng`) and ``dark_readings: bool`` (it needs LEDs-off reference
readings).
:class:`Effect` is the :class:`typing.Protocol`. A new effect (device optics, an LED droop, rain)
is one small frozen dataclass and one config (see docs/plugins.md).

The signal passes through three domains, in order; an effect works in one of them and moves the
signal on with :meth:`Signal.measured` or :meth:`Signal.read_out` when it needs to:

1. **image**: ``image_e`` (e⁻ per pixel from the active light), ``optical_depth`` (round-trip,
   per pixel) and its per-reading scale (fog fluctuation);
2. **readings**: ``pos_e``/``neg_e`` (e⁻ per reading of the split pattern pair) and the
   background charge ``bg_pos``/``bg_neg``/``bg_dark``;
3. **output**: ``y_pos``/``y_neg`` in detector units (ADC counts, or relative radiance for the
   ideal detector) with their ``gain``.

Built-in effects, in the order :func:`forward_model` chains them:

======================  ==========================  ==============================================
effect                  enabled by                  what it does
======================  ==========================  ==============================================
``budget``              ``detector=ingaas``          1/r² fall-off per pixel, LED power, lens, QE
                                                     (Eqs. 10–11): :class:`Illumination`
``fog``                 ``fog=chamber|measured``     e^{−2βr} per pixel, round trip (Eq. 6):
                                                     :class:`FogAttenuation`
``fog_fluctuation``     ``fog.fluctuation_rel > 0``  β(t) = β f(t) per reading: :class:`FogFluctuation`
``fog_trend``           ``fog.trend_rel != 0``       β(t) = β (1 + rel t/T): :class:`FogTrend`
``backscatter``         ``fog.backscatter_gain > 0`` veil of the lit fog (Eq. 12): :class:`Backscatter`
``led_droop``           ``source.effects.led_droop…``  LED power droop per reading: :class:`LedDroop`
``background``          ``illumination.klux > 0``    ambient charge (Eqs. 7, 10–11):
                                                     :class:`BackgroundLight`
``background_drift``    ``illumination.drift…``      drift, flicker, wander: :class:`BackgroundDrift`
``detector``            ``detector=ingaas``          shot/dark/read noise, saturation, ADC:
                                                     :class:`DetectorReadout`
``gaussian_noise``      ``source.effects.noise_rel``  idealised Gaussian noise: :class:`GaussianNoise`
======================  ==========================  ==============================================
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.detector import Photodiode
from nirspi_pipe.physics.light import Background

__all__ = [
    "Effect",
    "Exposure",
    "FogPath",
    "Signal",
    "Illumination",
    "FogAttenuation",
    "FogFluctuation",
    "FogTrend",
    "LedDroop",
    "Backscatter",
    "BackgroundLight",
    "BackgroundDrift",
    "DetectorReadout",
    "GaussianNoise",
    "forward_model",
    "split_measure",
    "modulated_split",
]


def split_measure(radiance: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free split measurements of ``radiance`` for the given flat pattern indices.

    Pattern ``P_k`` (±1) is shown as ``(1 + P_k)/2`` and ``(1 − P_k)/2``; with ``c_k = Σ P_k O``
    (Eq. 1, α = 1) and ``S = Σ O`` the two readings are ``(S + c_k)/2`` and ``(S − c_k)/2``.
    Units: radiance × pixels. Cost ``O(N log N)`` for all patterns at once.
    """
    coeffs = fwht2(radiance).ravel()[np.asarray(indices, dtype=np.int64)]
    total = float(radiance.sum())
    return 0.5 * (total + coeffs), 0.5 * (total - coeffs)


def modulated_split(
    base: np.ndarray, x: np.ndarray, c_pos: np.ndarray, c_neg: np.ndarray, indices: np.ndarray, tol: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """Split readings of ``base ⊙ exp(−c x)`` where the scalar ``c`` changes per reading.

    ``pos_k = Σ (1 + P_k)/2 ⊙ base ⊙ e^{−c_pos[k] x}``, ``neg_k`` likewise with ``(1 − P_k)/2``
    and ``c_neg[k]``. This is how a fog density that fluctuates during the acquisition
    (``β(t) = β f(t)``) acts on every pattern without building the patterns: around the
    base-weighted mean ``x₀``, ``e^{−c x} = e^{−c x₀} Σ_j (−c)^j (x − x₀)^j / j!``, one transform per
    term, truncated when the remainder bound is below ``tol`` (a handful of terms in practice).
    When ``|c (x − x₀)|`` exceeds 8 the series is replaced by exact transforms at 65 levels of
    ``c`` with linear interpolation between them.
    """
    import math

    idx = np.asarray(indices, dtype=np.int64)
    c_pos = np.asarray(c_pos, dtype=np.float64)
    c_neg = np.asarray(c_neg, dtype=np.float64)
    w = np.abs(base)
    x = np.where(w > 0, x, 0.0)
    x0 = float((w * x).sum() / w.sum()) if w.sum() > 0 else 0.0
    dx = np.where(w > 0, x - x0, 0.0)
    cmax = float(max(np.abs(c_pos).max(initial=0.0), np.abs(c_neg).max(initial=0.0)))
    amp = cmax * float(np.abs(dx).max(initial=0.0))
    if amp <= 8.0:
        pos = np.zeros(idx.size)
        neg = np.zeros(idx.size)
        term = base.astype(np.float64)
        w_pos = np.ones(idx.size)  # (−c)^j, updated in place
        w_neg = np.ones(idx.size)
        j = 0
        while True:
            f = fwht2(term).ravel()[idx]
            s = float(term.sum())
            pos += w_pos * (s + f)
            neg += w_neg * (s - f)
            bound = amp ** (j + 1) / math.factorial(j + 1) * math.exp(amp)
            if bound < tol or j >= 60:
                break
            j += 1
            term = term * dx / j
            w_pos *= -c_pos
            w_neg *= -c_neg
        pos *= 0.5
        neg *= 0.5
        return pos * np.exp(-c_pos * x0), neg * np.exp(-c_neg * x0)
    both = np.concatenate([c_pos, c_neg])
    levels = np.linspace(both.min(), both.max(), 65)
    f_lv = np.empty((levels.size, idx.size))
    s_lv = np.empty(levels.size)
    for i, c in enumerate(levels):
        img = base * np.exp(-c * x)
        f_lv[i] = fwht2(img).ravel()[idx]
        s_lv[i] = img.sum()

    def interp(c: np.ndarray, sign: float) -> np.ndarray:
        pos_in = np.clip(np.searchsorted(levels, c) - 1, 0, levels.size - 2)
        t = (c - levels[pos_in]) / np.maximum(levels[pos_in + 1] - levels[pos_in], 1e-300)
        k = np.arange(idx.size)
        lo = 0.5 * (s_lv[pos_in] + sign * f_lv[pos_in, k])
        hi = 0.5 * (s_lv[pos_in + 1] + sign * f_lv[pos_in + 1, k])
        return (1 - t) * lo + t * hi

    return interp(c_pos, 1.0), interp(c_neg, -1.0)


# --------------------------------------------------------------------------------------------
# What flows through the chain
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Exposure:
    """What is fixed during one acquisition; every effect may read it, none changes it.

    Attributes:
        scene: the rendered scene.
        indices: ``(m,)`` flat pattern indices, in measurement order.
        n: pattern side (pixels).
        t_pos, t_neg: ``(m,)`` times of the positive/negative half-pattern readings, s.
        t_dark: ``(n_dark,)`` times of the LEDs-off reference readings, s.
        budget: the camera's photon budget (Eqs. 10–11); the default one for an ideal detector.
        rngs: the independent random streams of the effects (:meth:`rng`).
        rng_main: the source's own generator (the idealised Gaussian noise draws from it).
    """

    scene: Any
    indices: np.ndarray
    n: int
    t_pos: np.ndarray
    t_neg: np.ndarray
    t_dark: np.ndarray
    budget: PhotonBudget
    rngs: tuple[np.random.Generator, ...] = ()
    rng_main: np.random.Generator | None = None

    @property
    def m(self) -> int:
        """Number of ±1 measurements (pattern pairs)."""
        return int(self.indices.size)

    @property
    def n_dark(self) -> int:
        """Number of LEDs-off reference readings."""
        return int(self.t_dark.size)

    @property
    def readings(self) -> int:
        """All readings taken: ``2 m + n_dark``."""
        return 2 * self.m + self.n_dark

    @cached_property
    def ref_e(self) -> float:
        """e⁻ per unit relative radiance per pixel at the scene's nominal distance in clear air."""
        return float(self.budget.white_electrons(float(self.scene.distance_m))) / (self.n * self.n)

    @cached_property
    def range_m(self) -> np.ndarray:
        """``(n, n)`` distance from the camera to the object along each pixel's ray, m (inf off it)."""
        u, v = self.scene.camera.pixel_coords(1)
        finite = np.isfinite(self.scene.depth_m)
        return np.where(finite, self.scene.depth_m * np.sqrt(1.0 + u[..., 0] ** 2 + v[..., 0] ** 2), np.inf)

    def rng(self, stream: int) -> np.random.Generator:
        """Random stream ``stream`` (0: fog fluctuation, 1: background drift, 2: detector; a
        plugin effect takes its own number >= 3 and declares it in ``streams``)."""
        if stream >= len(self.rngs):
            raise IndexError(f"random stream {stream} was not declared by any effect in the chain")
        return self.rngs[stream]


@dataclass(frozen=True)
class FogPath:
    """The fog between camera and object, as the fog effect set it up.

    Attributes:
        beta_per_m: extinction coefficient β, 1/m.
        path_m: ``(n, n)`` fog path along each ray, ``min(range, extent)``, m.
        extent_m: fog path length of the chamber, m.
        albedo: single-scattering albedo ``Q_sca/Q_ext``.
    """

    beta_per_m: float
    path_m: np.ndarray
    extent_m: float
    albedo: float


@dataclass(frozen=True)
class Signal:
    """The acquisition in progress (see the module docstring for the three domains).

    Charges are photoelectrons (e⁻). ``derived`` collects the physical quantities for the record;
    ``conditions`` the keyword conditions of Algorithm A1 (:func:`range_model.max_distance_m`).
    """

    image_e: np.ndarray
    optical_depth: np.ndarray | None = None
    depth_scale_pos: np.ndarray | None = None
    depth_scale_neg: np.ndarray | None = None
    medium: FogPath | None = None
    pos_e: np.ndarray | None = None
    neg_e: np.ndarray | None = None
    background_e: float = 0.0
    bg_pos: float | np.ndarray | None = None
    bg_neg: float | np.ndarray | None = None
    bg_dark: float | np.ndarray | None = None
    y_pos: np.ndarray | None = None
    y_neg: np.ndarray | None = None
    gain: float = 1.0
    noise_e: float = 0.0
    saturated: int = 0
    derived: Mapping[str, Any] = field(default_factory=dict)
    conditions: Mapping[str, float] = field(default_factory=dict)

    def with_derived(self, **values: Any) -> Signal:
        """The same signal with more quantities for the record."""
        return replace(self, derived={**self.derived, **values})

    @property
    def beta_per_m(self) -> float:
        """β of the medium, 1/m (0 in clear air)."""
        return self.medium.beta_per_m if self.medium is not None else 0.0

    def measured(self, exposure: Exposure) -> Signal:
        """Move from the image domain to readings: the split patterns measure the attenuated
        image (``image_e ⊙ e^{−τ}``, with a per-reading scale of ``τ`` when the fog fluctuates)."""
        if self.pos_e is not None:
            return self
        idx = exposure.indices
        if self.optical_depth is None:
            pos, neg = split_measure(self.image_e, idx)
        elif self.depth_scale_pos is None or self.depth_scale_neg is None:
            pos, neg = split_measure(self.image_e * np.exp(-self.optical_depth), idx)
        else:
            pos, neg = modulated_split(
                self.image_e, self.optical_depth, self.depth_scale_pos, self.depth_scale_neg, idx
            )
        return replace(self, pos_e=pos, neg_e=neg)

    @property
    def signal_mean_e(self) -> float:
        """Mean active-light charge per reading (before background), e⁻."""
        if self.pos_e is None or self.neg_e is None or self.pos_e.size == 0:
            return 0.0
        return float(0.5 * (self.pos_e.mean() + self.neg_e.mean()))

    def total_e(self) -> tuple[np.ndarray, np.ndarray]:
        """Charge per reading, active light plus background, e⁻ (after :meth:`measured`)."""
        if self.pos_e is None or self.neg_e is None:
            raise RuntimeError("total_e() before measured()")
        if self.bg_pos is None or self.bg_neg is None:
            return self.pos_e, self.neg_e
        return self.pos_e + self.bg_pos, self.neg_e + self.bg_neg

    def read_out(self, exposure: Exposure) -> Signal:
        """Move to the output domain. Without a detector effect the readings are relative
        radiance: charge divided by :attr:`Exposure.ref_e`, gain 1, no noise."""
        if self.y_pos is not None:
            return self
        s = self.measured(exposure)
        pos, neg = s.total_e()
        ref = exposure.ref_e
        return replace(s, y_pos=pos / ref, y_neg=neg / ref, gain=1.0)


@runtime_checkable
class Effect(Protocol):
    """One physical effect of the forward model (module docstring). ``name`` may be a class
    attribute (``name: ClassVar[str] = "rain"``) or a field."""

    @property
    def name(self) -> str: ...

    def apply(self, signal: Signal, exposure: Exposure) -> Signal: ...


def _check_rel(key: str, value: float, lo: float, hi: float, what: str) -> None:
    if not np.isfinite(value) or not lo <= value <= hi:
        raise ConfigError(key, value, what)


# --------------------------------------------------------------------------------------------
# The built-in effects
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Illumination:
    """The active light and photon budget: each pixel gets ``ρ N_white(r)/n²`` e⁻ with the
    1/r² fall-off of its own range ``r`` (Eqs. 10–11). Without it (ideal detector) every pixel
    gets ``ρ N_white(z_nom)/n²``: no fall-off across the object."""

    budget: PhotonBudget = field(default_factory=PhotonBudget)

    name: ClassVar[str] = "budget"
    #: part of the noise-free static image the metrics compare against (``Simulator.reference_image``)
    reference: ClassVar[bool] = True

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        r = exposure.range_m
        finite = np.isfinite(r)
        n2 = exposure.n * exposure.n
        img = (
            exposure.scene.radiance * np.where(finite, self.budget.white_electrons(np.where(finite, r, 1.0)), 0.0) / n2
        )
        return replace(signal, image_e=img)


@dataclass(frozen=True)
class FogAttenuation:
    """Beer–Lambert on the round trip through the fog: optical depth ``2 β min(r, extent)`` per
    pixel (Eq. 6). The fog fills the chamber from the camera to ``extent`` (35 cm, §4); beyond it
    the air is clear. ``fog`` is a fog model of :mod:`nirspi_pipe.physics.fog` (``extinction_per_m``,
    ``extent_m``, ``derived()``)."""

    fog: Any

    name: ClassVar[str] = "fog"
    reference: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not hasattr(type(self.fog), "extinction_per_m") or not hasattr(self.fog, "extent_m"):
            raise ConfigError("fog", self.fog, "a fog model exposing extinction_per_m and extent_m (conf/fog)")

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        fog = self.fog
        beta = float(fog.extinction_per_m)
        r = exposure.range_m
        path = np.minimum(r, float(fog.extent_m))  # the fog path of each ray (inf off the object)
        x = np.where(np.isfinite(r), 2.0 * beta * np.where(np.isfinite(path), path, 0.0), 0.0)
        albedo = float(getattr(fog, "single_scattering_albedo", 1.0))
        medium = FogPath(beta, np.minimum(r, fog.extent_m), float(fog.extent_m), albedo)
        cond = {
            **signal.conditions,
            "backscatter_gain": float(getattr(fog, "backscatter_gain", 0.0)),
            "fog_extent_m": float(fog.extent_m),
            "albedo": albedo,
        }
        derived = fog.derived() if hasattr(fog, "derived") else {"beta_per_m": beta}
        return replace(signal, optical_depth=x, medium=medium, conditions=cond).with_derived(**derived)


@dataclass(frozen=True)
class FogFluctuation:
    """The fog density changes during the acquisition: ``β(t) = β f(t)`` with ``f = 1 + OU``
    (Ornstein–Uhlenbeck of relative std ``rel`` and correlation time ``time_s``), per reading."""

    rel: float
    time_s: float = 0.05

    name: ClassVar[str] = "fog_fluctuation"
    streams: ClassVar[tuple[int, ...]] = (0,)

    def __post_init__(self) -> None:
        _check_rel("fluctuation_rel", self.rel, 0.0, 1.0, "a relative standard deviation in [0, 1]")
        if not np.isfinite(self.time_s) or self.time_s <= 0:
            raise ConfigError("fluctuation_time_s", self.time_s, "a correlation time in s > 0")

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        from nirspi_pipe.physics.timevarying import fog_factor

        if signal.optical_depth is None:
            raise ValueError("fog_fluctuation must follow the fog effect in the chain")
        m = exposure.m
        f_all = fog_factor(np.concatenate([exposure.t_pos, exposure.t_neg]), exposure.rng(0), self.rel, self.time_s)
        return replace(signal, depth_scale_pos=f_all[:m], depth_scale_neg=f_all[m:]).with_derived(
            fog_factor_std=float(np.std(f_all))
        )


@dataclass(frozen=True)
class FogTrend:
    """The fog density trends during the acquisition: ``β(t) = β (1 + rel · t/T)`` per reading,
    linear from the first reading (t = 0) to the last (t = T), multiplying any fluctuation. A
    multiplicative drift: its error depends on the image, and the scan order decides which
    coefficients see the early and the late density (issue 11). ``rel`` is ``fog.trend_rel``."""

    rel: float

    name: ClassVar[str] = "fog_trend"

    def __post_init__(self) -> None:
        _check_rel("trend_rel", self.rel, -0.9, 10.0, "a relative change over the acquisition in [-0.9, 10]")

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        if signal.optical_depth is None:
            raise ValueError("fog_trend must follow the fog effect in the chain")
        t_end = float(max(exposure.t_neg.max(initial=0.0), exposure.t_dark.max(initial=0.0)))
        scale = 1.0 / t_end if t_end > 0 else 0.0
        f_pos = 1.0 + self.rel * exposure.t_pos * scale
        f_neg = 1.0 + self.rel * exposure.t_neg * scale
        if signal.depth_scale_pos is not None and signal.depth_scale_neg is not None:
            f_pos, f_neg = f_pos * signal.depth_scale_pos, f_neg * signal.depth_scale_neg
        return replace(signal, depth_scale_pos=f_pos, depth_scale_neg=f_neg).with_derived(fog_trend_rel=self.rel)


@dataclass(frozen=True)
class LedDroop:
    """The LED array's output droops as the junctions warm during the acquisition:
    ``P(t) = P₀ (1 + rel (1 − e^{−t/τ}))`` (``rel < 0``: droop), on the active light of every
    reading (object and fog veil; not the background). InGaAsP LEDs lose output with junction
    temperature (a negative temperature coefficient of optical power, e.g. Thorlabs LED1550E
    datasheet); the amount and τ here are study values (``source.effects.led_droop_rel``,
    ``led_droop_time_s``), not measured on the paper's camera."""

    rel: float
    time_s: float = 0.05

    name: ClassVar[str] = "led_droop"

    def __post_init__(self) -> None:
        _check_rel("led_droop_rel", self.rel, -0.9, 1.0, "a relative change of LED power in [-0.9, 1]")
        if not np.isfinite(self.time_s) or self.time_s <= 0:
            raise ConfigError("led_droop_time_s", self.time_s, "a thermal time constant in s > 0")

    def factor(self, t_s: np.ndarray) -> np.ndarray:
        """Relative LED power at times ``t_s`` (s), dimensionless."""
        return 1.0 + self.rel * -np.expm1(-np.asarray(t_s, dtype=np.float64) / self.time_s)

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        s = signal.measured(exposure)
        assert s.pos_e is not None and s.neg_e is not None
        return replace(s, pos_e=s.pos_e * self.factor(exposure.t_pos), neg_e=s.neg_e * self.factor(exposure.t_neg))


@dataclass(frozen=True)
class Backscatter:
    """The veil of light scattered back by the lit fog (Eq. 12): ``κ N_white(1 m) (1 − e^{−β ℓ})``
    on every reading, with ``ℓ`` the fog path of each pixel and κ = ``gain``."""

    gain: float

    name: ClassVar[str] = "backscatter"

    def __post_init__(self) -> None:
        _check_rel("backscatter_gain", self.gain, 0.0, np.inf, "a factor >= 0")

    def veil_e(self, medium: FogPath, exposure: Exposure) -> np.ndarray:
        """``(n, n)`` steady veil per pixel, e⁻: ``κ N_white(1 m)/n² (1 − e^{−β ℓ})``  # Eq. (12)."""
        from nirspi_pipe.physics.fog import backscatter

        white_1m = float(exposure.budget.white_electrons(1.0)) / (exposure.n * exposure.n)
        veil = backscatter(self.gain, white_1m, medium.beta_per_m, medium.path_m)
        return np.asarray(veil, dtype=np.float64) * np.ones(exposure.scene.radiance.shape)

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        med = signal.medium
        if med is None:
            raise ValueError("backscatter must follow the fog effect in the chain")
        idx = exposure.indices
        white_1m = float(exposure.budget.white_electrons(1.0)) / (exposure.n * exposure.n)
        shape = exposure.scene.radiance.shape
        s = signal.measured(exposure)
        if s.depth_scale_pos is None or s.depth_scale_neg is None:
            veil_pos, veil_neg = split_measure(self.veil_e(med, exposure), idx)
        else:  # Eq. (12) with β(t): κ N_white(1 m) (1 − e^{−β(t) ℓ})
            k = np.full(shape, self.gain * white_1m)
            a_pos, a_neg = split_measure(k, idx)
            b_pos, b_neg = modulated_split(k, med.beta_per_m * med.path_m, s.depth_scale_pos, s.depth_scale_neg, idx)
            veil_pos, veil_neg = a_pos - b_pos, a_neg - b_neg
        assert s.pos_e is not None and s.neg_e is not None
        per_pattern = float(0.5 * (veil_pos.mean() + veil_neg.mean())) if exposure.m else 0.0
        return replace(s, pos_e=s.pos_e + veil_pos, neg_e=s.neg_e + veil_neg).with_derived(
            backscatter_photons_per_pattern=per_pattern
        )


@dataclass(frozen=True)
class BackgroundLight:
    """Ambient light (Eqs. 7, 10–11): the same charge on every reading, from the scene's mean
    reflectance (object and surround, seen through the fog's airlight by Koschmieder when the
    fog effect is in the chain before it). ``background`` is a
    :class:`~nirspi_pipe.physics.light.Background`."""

    background: Background

    name: ClassVar[str] = "background"

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        from nirspi_pipe.physics.fog import koschmieder_radiance

        bg, scene, med = self.background, exposure.scene, signal.medium
        cov = scene.coverage
        if med is not None:
            path = np.where(np.isfinite(med.path_m), med.path_m, 0.0)
            obj = koschmieder_radiance(scene.reflectance, med.albedo, med.beta_per_m, path)
            wall = koschmieder_radiance(bg.surround_reflectance, med.albedo, med.beta_per_m, med.extent_m)
        else:
            obj, wall = scene.reflectance, np.asarray(bg.surround_reflectance)
        refl = float(np.mean(cov * obj + (1.0 - cov) * wall))
        bg_e = float(exposure.budget.ambient_electrons(bg.photon_irradiance, refl))
        s = signal.measured(exposure)
        return replace(
            s,
            background_e=bg_e,
            bg_pos=bg_e,
            bg_neg=bg_e,
            bg_dark=bg_e,
            conditions={**s.conditions, "photon_irradiance": float(bg.photon_irradiance)},
        ).with_derived(klux=float(bg.klux), background_irradiance_w_m2=float(bg.irradiance_w_m2))


@dataclass(frozen=True)
class BackgroundDrift:
    """The background level changes during the acquisition: ``1 + drift·t + flicker·sin(2πft + φ)
    + OU`` per reading (:func:`~nirspi_pipe.physics.timevarying.background_factor`), so it no
    longer cancels exactly in ``y_pos − y_neg``."""

    drift_rel_per_s: float = 0.0
    flicker_rel: float = 0.0
    flicker_hz: float = 100.0
    wander_rel: float = 0.0
    wander_time_s: float = 0.1

    name: ClassVar[str] = "background_drift"
    streams: ClassVar[tuple[int, ...]] = (1,)

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        from nirspi_pipe.physics.timevarying import background_factor

        if signal.bg_pos is None:
            raise ValueError("background_drift must follow the background effect in the chain")
        m = exposure.m
        fac = background_factor(
            np.concatenate([exposure.t_pos, exposure.t_neg, exposure.t_dark]),
            exposure.rng(1),
            self.drift_rel_per_s,
            self.flicker_rel,
            self.flicker_hz,
            self.wander_rel,
            self.wander_time_s,
        )
        bg_e = signal.background_e
        return replace(
            signal, bg_pos=bg_e * fac[:m], bg_neg=bg_e * fac[m : 2 * m], bg_dark=bg_e * fac[2 * m :]
        ).with_derived(background_factor_std=float(np.std(fac)))


@dataclass(frozen=True)
class DetectorReadout:
    """The InGaAs photodiode reads every reading: shot, dark and read noise, pedestal, saturation
    (counted and warned about, never hidden) and ADC (:class:`~nirspi_pipe.physics.detector.Photodiode`).
    Also takes the LEDs-off reference readings and records Algorithm A1's range."""

    detector: Photodiode

    name: ClassVar[str] = "detector"
    streams: ClassVar[tuple[int, ...]] = (2,)
    dark_readings: ClassVar[bool] = True

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        det = self.detector
        rng = exposure.rng(2)
        s = signal.measured(exposure)
        pos_e, neg_e = s.total_e()
        m, n_dark = exposure.m, exposure.n_dark
        signal_mean = s.signal_mean_e
        epc = det.electrons_per_count
        y_pos, sat_pos = det.read(pos_e, rng)
        y_neg, sat_neg = det.read(neg_e, rng)
        saturated = int(sat_pos.sum() + sat_neg.sum())
        derived: dict[str, Any] = dict(
            read_noise_e=float(det.read_noise_e),
            dark_electrons=float(det.dark_electrons),
            electrons_per_count=float(epc),
            led_count=int(exposure.budget.led_count),
            noise_photons_per_pattern=float(det.noise_e(signal_mean + s.background_e)),
        )
        if det.full_scale_e is not None:
            derived["full_scale_e"] = float(det.full_scale_e)
        if n_dark:
            bg_dark = 0.0 if s.bg_dark is None else s.bg_dark
            dark_counts, sat_dark = det.read(np.broadcast_to(bg_dark, (n_dark,)) + 0.0, rng)
            saturated += int(sat_dark.sum())
            if m:
                derived["measured_signal_e"] = float((np.mean(y_pos + y_neg) - 2.0 * np.mean(dark_counts)) * epc)
        if m >= 2:
            derived["measured_noise_e"] = float(np.std(y_pos + y_neg, ddof=1) / np.sqrt(2.0) * epc)
        if saturated:
            warnings.warn(
                f"{saturated} of {exposure.readings} readings saturated the detector (full scale "
                f"{det.full_scale_e:.3g} e-); reduce klux, LED power or move the object away",
                stacklevel=2,
            )
        derived.update(self._range(exposure, s))
        return replace(
            s,
            y_pos=y_pos,
            y_neg=y_neg,
            gain=exposure.ref_e / epc,
            saturated=saturated,
            noise_e=float(derived["noise_photons_per_pattern"]),
        ).with_derived(**derived)

    def _range(self, exposure: Exposure, signal: Signal) -> dict[str, float]:
        """Alg. A1 for this configuration and the object's mean reflectance."""
        from nirspi_pipe.physics.range_model import max_distance_m

        scene = exposure.scene
        obj = scene.mask if scene.mask.any() else scene.coverage > 0
        if not obj.any():
            return {}
        refl = float(np.clip(scene.reflectance[obj].mean(), 0.0, 1.0))
        cond = {"beta_per_m": signal.beta_per_m, **signal.conditions}
        return {"range_max_m": max_distance_m(refl, self.detector, **cond), "range_reflectance": refl}


@dataclass(frozen=True)
class GaussianNoise:
    """Idealised additive Gaussian noise on every reading (output units), of std ``noise_rel``
    times the mean noise-free half-pattern reading (the foundation's noise model)."""

    noise_rel: float

    name: ClassVar[str] = "gaussian_noise"

    def __post_init__(self) -> None:
        _check_rel("noise_rel", self.noise_rel, 0.0, np.inf, "a relative noise level >= 0")

    def apply(self, signal: Signal, exposure: Exposure) -> Signal:
        s = signal.read_out(exposure)
        rng = exposure.rng_main if exposure.rng_main is not None else np.random.default_rng(0)
        assert s.y_pos is not None and s.y_neg is not None
        sigma = self.noise_rel * 0.5 * float(exposure.scene.radiance.sum()) * s.gain
        y_pos = s.y_pos + rng.normal(0.0, sigma, s.y_pos.shape)
        y_neg = s.y_neg + rng.normal(0.0, sigma, s.y_neg.shape)
        noise_e = float(np.hypot(s.noise_e, sigma * (exposure.ref_e / s.gain)))
        return replace(s, y_pos=y_pos, y_neg=y_neg, noise_e=noise_e).with_derived(noise_sigma=float(sigma))


# --------------------------------------------------------------------------------------------
# Building the chain from the config groups
# --------------------------------------------------------------------------------------------


def _active(model: Any) -> bool:
    return model is not None and bool(getattr(model, "active", True))


def forward_model(
    fog: Any = None,
    illumination: Background | None = None,
    detector: Any = None,
    noise_rel: float = 0.0,
    extra: Sequence[Effect] = (),
    led_droop_rel: float = 0.0,
    led_droop_time_s: float = 0.05,
) -> tuple[Effect, ...]:
    """The ordered chain of the effects that the models enable (off effects are left out).

    Args:
        fog: a fog model (``fog=chamber|measured``; ``NoFog`` or None: clear air).
        illumination: the background light (0 kLux or None: none).
        detector: ``Photodiode`` (budget + readout effects) or ``IdealDetector``/None.
        noise_rel: idealised Gaussian noise, relative (0: none).
        led_droop_rel, led_droop_time_s: LED power droop during the acquisition (:class:`LedDroop`;
            0: none).
        extra: further effects (plugins), in the order given, each placed by its ``domain``:
            ``"image"`` after the fog attenuation (before anything is measured), ``"readings"``
            (the default) after the background light and before the detector, ``"output"`` at
            the end.
    """
    if detector is not None and not hasattr(detector, "physical"):
        raise ConfigError("detector", detector, "a detector from conf/detector (ideal, ingaas)")
    _check_rel("noise_rel", noise_rel, 0.0, np.inf, "a relative noise level >= 0")
    placed: dict[str, list[Effect]] = {"image": [], "readings": [], "output": []}
    for effect in extra:
        where = getattr(effect, "domain", "readings")
        if not isinstance(effect, Effect) or where not in placed:
            raise ConfigError(
                "extra", effect, "effects with a name, apply(signal, exposure) and domain image, readings or output"
            )
        placed[where].append(effect)
    _check_rel("led_droop_rel", led_droop_rel, -0.9, 1.0, "a relative change of LED power in [-0.9, 1]")
    physical = bool(getattr(detector, "physical", False))
    chain: list[Effect] = []
    if physical:
        chain.append(Illumination(detector.budget))
    if _active(fog):
        chain.append(FogAttenuation(fog))
        if float(getattr(fog, "fluctuation_rel", 0.0)) > 0:
            chain.append(FogFluctuation(float(fog.fluctuation_rel), float(fog.fluctuation_time_s)))
        if float(getattr(fog, "trend_rel", 0.0)) != 0:
            chain.append(FogTrend(float(fog.trend_rel)))
    chain += placed["image"]
    if _active(fog) and float(getattr(fog, "backscatter_gain", 0.0)) > 0:
        chain.append(Backscatter(float(fog.backscatter_gain)))
    if led_droop_rel != 0:
        chain.append(LedDroop(float(led_droop_rel), float(led_droop_time_s)))
    if _active(illumination):
        assert illumination is not None
        chain.append(BackgroundLight(illumination))
        if illumination.time_varying:
            chain.append(
                BackgroundDrift(
                    illumination.drift_rel_per_s,
                    float(illumination.flicker_rel or 0.0),
                    illumination.flicker_hz,
                    illumination.wander_rel,
                    illumination.wander_time_s,
                )
            )
    chain += placed["readings"]
    if physical:
        chain.append(DetectorReadout(detector))
    if noise_rel > 0:
        chain.append(GaussianNoise(float(noise_rel)))
    chain += placed["output"]
    return tuple(chain)
