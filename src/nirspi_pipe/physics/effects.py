"""The forward model in typed stages (paper §§3–5, Eqs. 5–12): the built-in effects and the chain.

The simulator (:class:`nirspi_pipe.sources.simulator.Simulator`) runs a :class:`ForwardModel`;
:func:`forward_model` builds the one that the config groups ``fog``, ``illumination`` and
``detector`` enable. An effect that is off is not in it, so it costs nothing.

The stages
----------
The model runs in typed stages (:mod:`nirspi_pipe.physics.stagetypes` defines the hand-offs and the
protocols; plugins import them from there)::

    image effects ─► measure ─► reading effects ─► read-out ─► output effects
    ImageState        Readings                      Output

1. **image** (:class:`ImageEffect`: ``apply(ImageState, Exposure) -> ImageState``): ``image_e``
   (e⁻ per pixel from the active light) and the fog (:class:`FogPath`: round-trip optical depth per
   pixel, and its per-reading scale when the fog fluctuates);
2. :func:`measure`: the split patterns measure ``image_e ⊙ e^{−τ}``;
3. **readings** (:class:`ReadingEffect`: ``apply(Readings, Exposure) -> Readings``): ``pos_e``/
   ``neg_e`` (e⁻ per reading of the split pattern pair) and the ambient charge
   (:class:`AmbientCharge`);
4. the read-out (:class:`ReadOut`: the photodiode, :class:`DetectorReadout`; without one,
   :func:`ideal_readout`: relative radiance);
5. **output** (:class:`OutputEffect`: ``apply(Output, Exposure) -> Output``): ``y_pos``/``y_neg``
   in detector units (ADC counts, or relative radiance for the ideal detector) with their ``gain``.

Every effect has a ``name`` and declares its stage (``domain``); image and reading effects declare
``in_reference`` (part of the noise-free reference the normalised metrics score against,
:meth:`ForwardModel.reference_e`), and may declare ``streams: tuple[int, ...]`` (the random
streams they draw from, :meth:`Exposure.rng`). A new effect (device optics, an LED droop, rain) is
one small frozen dataclass and one config (docs/plugins.md).

Built-in effects, in the order :func:`forward_model` chains them (name, class, what enables it,
whether it is in the reference; the effects of light, :class:`Illumination`, :class:`BackgroundLight`
and :class:`BackgroundDrift`, are in :mod:`nirspi_pipe.physics.lighteffects`):

* image stage

  - ``budget``, :class:`Illumination` (``detector=ingaas``): 1/r² fall-off per pixel, LED power,
    lens, QE (Eqs. 10–11); in the reference;
  - ``fog``, :class:`FogAttenuation` (``fog=chamber|measured``): e^{−2βr} per pixel, round trip
    (Eq. 6); in the reference;
  - ``fog_fluctuation``, :class:`FogFluctuation` (``fog.fluctuation_rel > 0``): β(t) = β f(t)
    per reading; not in the reference;
  - ``fog_trend``, :class:`FogTrend` (``fog.trend_rel != 0``): β(t) = β (1 + rel t/T); not in
    the reference;

* readings stage

  - ``backscatter``, :class:`Backscatter` (``fog.backscatter_gain > 0``): veil of the lit fog
    (Eq. 12); in the reference (its steady veil);
  - ``led_droop``, :class:`LedDroop` (``source.effects.led_droop_rel != 0``): LED power droop per
    reading; not in the reference;
  - ``background``, :class:`BackgroundLight` (``illumination.klux > 0``): ambient charge
    (Eqs. 7, 10–11); not in the reference (it cancels in the split difference);
  - ``background_drift``, :class:`BackgroundDrift` (``illumination.drift…``): drift, flicker,
    wander; not in the reference;

* read-out: ``detector``, :class:`DetectorReadout` (``detector=ingaas``): shot/dark/read noise,
  saturation, ADC;
* output stage: ``gaussian_noise``, :class:`GaussianNoise` (``source.effects.noise_rel > 0``):
  idealised Gaussian noise.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Annotated, Any, ClassVar, Literal, cast

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.detector import Photodiode
from nirspi_pipe.physics.fog import backscatter
from nirspi_pipe.physics.light import Background
from nirspi_pipe.physics.lighteffects import BackgroundDrift, BackgroundLight, Illumination
from nirspi_pipe.physics.range_model import max_distance_m
from nirspi_pipe.physics.splitmeasure import modulated_split, split_measure
from nirspi_pipe.physics.stagetypes import (
    STAGES,
    AnyEffect,
    Effect,
    Exposure,
    FogPath,
    ImageEffect,
    ImageState,
    Output,
    OutputEffect,
    ReadingEffect,
    Readings,
    ReadOut,
    ReferenceReadingEffect,
    ideal_readout,
    measure,
    stage_of,
)
from nirspi_pipe.physics.timevarying import fog_factor
from nirspi_pipe.ranges import Range, check_ranges, check_value

__all__ = [
    "FogAttenuation",
    "FogFluctuation",
    "FogTrend",
    "LedDroop",
    "Backscatter",
    "DetectorReadout",
    "GaussianNoise",
    "ForwardModel",
    "forward_model",
]


#: Largest ``noise_rel`` (std of the added noise over the mean noise-free half-pattern reading).
#: Assumed: at 1e6 every reading is 10⁶ times noisier than the signal (SNR -120 dB), pure noise
#: already; far above it the image's squares overflow float64 in the scores (measured at 8²:
#: 1e50 finished, 1e100 and 1e300 overflowed in SSIM), so the bound keeps 40 decades of margin.
NOISE_REL_MAX = 1e6

#: The effects' declared ranges (:mod:`nirspi_pipe.ranges`), each under the config key that sets it.
NOISE_REL = Range(0.0, NOISE_REL_MAX, "a relative noise level", key="noise_rel")
#: Assumed: a droop/rise beyond -90 %/+100 % of the LED's power is no longer a thermal drift.
LED_DROOP_REL = Range(-0.9, 1.0, "a relative change of LED power", key="led_droop_rel")


# --------------------------------------------------------------------------------------------
# The built-in effects: image stage
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FogAttenuation:
    """Beer–Lambert on the round trip through the fog: optical depth ``2 β min(r, extent)`` per
    pixel (Eq. 6). The fog fills the chamber from the camera to ``extent`` (35 cm, §4); beyond it
    the air is clear. ``fog`` is a fog model of :mod:`nirspi_pipe.physics.fog` (``extinction_per_m``,
    ``extent_m``, ``derived()``). In the reference."""

    fog: Any

    name: ClassVar[str] = "fog"
    domain: ClassVar[Literal["image"]] = "image"
    in_reference: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not hasattr(type(self.fog), "extinction_per_m") or not hasattr(self.fog, "extent_m"):
            raise ConfigError("fog", self.fog, "a fog model exposing extinction_per_m and extent_m (conf/fog)")

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        fog = self.fog
        beta = float(fog.extinction_per_m)
        r = exposure.range_m
        path = np.minimum(r, float(fog.extent_m))  # the fog path of each ray (inf off the object)
        x = np.where(np.isfinite(r), 2.0 * beta * np.where(np.isfinite(path), path, 0.0), 0.0)
        albedo = float(getattr(fog, "single_scattering_albedo", 1.0))
        medium = FogPath(
            beta_per_m=beta,
            path_m=np.minimum(r, fog.extent_m),
            extent_m=float(fog.extent_m),
            albedo=albedo,
            optical_depth=x,
        )
        cond = {
            **image.conditions,
            "backscatter_gain": float(getattr(fog, "backscatter_gain", 0.0)),
            "fog_extent_m": float(fog.extent_m),
            "albedo": albedo,
        }
        derived = fog.derived() if hasattr(fog, "derived") else {"beta_per_m": beta}
        return replace(image, medium=medium, conditions=cond).with_derived(**derived)


def _fog_of(image: ImageState, effect: str) -> FogPath:
    if image.medium is None:
        raise ValueError(f"{effect} must follow the fog effect in the chain")
    return image.medium


@dataclass(frozen=True)
class FogFluctuation:
    """The fog density changes during the acquisition: ``β(t) = β f(t)`` with ``f = 1 + OU``
    (Ornstein–Uhlenbeck of relative std ``rel`` and correlation time ``time_s``), per reading.
    Not in the reference (it changes during the acquisition)."""

    rel: Annotated[float, Range(0.0, 1.0, "a relative standard deviation", key="fluctuation_rel")]
    time_s: Annotated[float, Range(0.0, None, "a correlation time in s", lo_open=True, key="fluctuation_time_s")] = 0.05

    name: ClassVar[str] = "fog_fluctuation"
    domain: ClassVar[Literal["image"]] = "image"
    in_reference: ClassVar[bool] = False
    streams: ClassVar[tuple[int, ...]] = (0,)

    def __post_init__(self) -> None:
        check_ranges(self)

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        med = _fog_of(image, "fog_fluctuation")
        m = exposure.m
        f_all = fog_factor(np.concatenate([exposure.t_pos, exposure.t_neg]), exposure.rng(0), self.rel, self.time_s)
        return replace(image, medium=replace(med, fluctuation=(f_all[:m], f_all[m:]))).with_derived(
            fog_factor_std=float(np.std(f_all))
        )


@dataclass(frozen=True)
class FogTrend:
    """The fog density trends during the acquisition: ``β(t) = β (1 + rel · t/T)`` per reading,
    linear from the first reading (t = 0) to the last (t = T), multiplying any fluctuation. A
    multiplicative drift: its error depends on the image, and the scan order decides which
    coefficients see the early and the late density (issue 11). ``rel`` is ``fog.trend_rel``.
    Not in the reference."""

    rel: Annotated[float, Range(-0.9, 10.0, "a relative change over the acquisition", key="trend_rel")]

    name: ClassVar[str] = "fog_trend"
    domain: ClassVar[Literal["image"]] = "image"
    in_reference: ClassVar[bool] = False

    def __post_init__(self) -> None:
        check_ranges(self)

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        med = _fog_of(image, "fog_trend")
        t_end = float(max(exposure.t_neg.max(initial=0.0), exposure.t_dark.max(initial=0.0)))
        scale = 1.0 / t_end if t_end > 0 else 0.0
        f_pos = 1.0 + self.rel * exposure.t_pos * scale
        f_neg = 1.0 + self.rel * exposure.t_neg * scale
        if med.fluctuation is not None:
            f_pos, f_neg = f_pos * med.fluctuation[0], f_neg * med.fluctuation[1]
        return replace(image, medium=replace(med, fluctuation=(f_pos, f_neg))).with_derived(fog_trend_rel=self.rel)


# --------------------------------------------------------------------------------------------
# The built-in effects: readings stage
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Backscatter:
    """The veil of light scattered back by the lit fog (Eq. 12): ``κ N_white(1 m) (1 − e^{−β ℓ})``
    on every reading, with ``ℓ`` the fog path of each pixel and κ = ``gain``. In the reference:
    its steady veil is added per pixel (:meth:`reference_e`)."""

    gain: Annotated[float, Range(0.0, None, "a factor", key="backscatter_gain")]

    name: ClassVar[str] = "backscatter"
    domain: ClassVar[Literal["readings"]] = "readings"
    in_reference: ClassVar[bool] = True

    def __post_init__(self) -> None:
        check_ranges(self)

    def veil_e(self, medium: FogPath, exposure: Exposure) -> np.ndarray:
        """``(n, n)`` steady veil per pixel, e⁻: ``κ N_white(1 m)/n² (1 − e^{−β ℓ})``  # Eq. (12)."""
        white_1m = float(exposure.budget.white_electrons(1.0)) / (exposure.n * exposure.n)
        veil = backscatter(self.gain, white_1m, medium.beta_per_m, medium.path_m)
        return np.asarray(veil, dtype=np.float64) * np.ones(exposure.scene.radiance.shape)

    def reference_e(self, image_e: np.ndarray, image: ImageState, exposure: Exposure) -> np.ndarray:
        """The reference with the steady veil (:meth:`veil_e`) added per pixel, e⁻."""
        if image.medium is None:
            return image_e
        return image_e + self.veil_e(image.medium, exposure)

    def apply(self, readings: Readings, exposure: Exposure) -> Readings:
        med = readings.medium
        if med is None:
            raise ValueError("backscatter must follow the fog effect in the chain")
        idx = exposure.indices
        white_1m = float(exposure.budget.white_electrons(1.0)) / (exposure.n * exposure.n)
        shape = exposure.scene.radiance.shape
        if med.fluctuation is None:
            veil_pos, veil_neg = split_measure(self.veil_e(med, exposure), idx)
        else:  # Eq. (12) with β(t): κ N_white(1 m) (1 − e^{−β(t) ℓ})
            k = np.full(shape, self.gain * white_1m)
            a_pos, a_neg = split_measure(k, idx)
            b_pos, b_neg = modulated_split(k, med.beta_per_m * med.path_m, *med.fluctuation, idx)
            veil_pos, veil_neg = a_pos - b_pos, a_neg - b_neg
        per_pattern = float(0.5 * (veil_pos.mean() + veil_neg.mean())) if exposure.m else 0.0
        return replace(readings, pos_e=readings.pos_e + veil_pos, neg_e=readings.neg_e + veil_neg).with_derived(
            backscatter_photons_per_pattern=per_pattern
        )


@dataclass(frozen=True)
class LedDroop:
    """The LED array's output droops as the junctions warm during the acquisition:
    ``P(t) = P₀ (1 + rel (1 − e^{−t/τ}))`` (``rel < 0``: droop), on the active light of every
    reading (object and fog veil; not the background). InGaAsP LEDs lose output with junction
    temperature (a negative temperature coefficient of optical power, e.g. Thorlabs LED1550E
    datasheet); the amount and τ here are study values (``source.effects.led_droop_rel``,
    ``led_droop_time_s``), not measured on the paper's camera. Not in the reference."""

    rel: Annotated[float, LED_DROOP_REL]
    time_s: Annotated[float, Range(0.0, None, "a thermal time constant in s", lo_open=True, key="led_droop_time_s")] = (
        0.05
    )

    name: ClassVar[str] = "led_droop"
    domain: ClassVar[Literal["readings"]] = "readings"
    in_reference: ClassVar[bool] = False

    def __post_init__(self) -> None:
        check_ranges(self)

    def factor(self, t_s: np.ndarray) -> np.ndarray:
        """Relative LED power at times ``t_s`` (s), dimensionless."""
        with np.errstate(over="ignore"):  # t/τ beyond float64 is the settled droop: exp(-inf) = 0
            return 1.0 + self.rel * -np.expm1(-np.asarray(t_s, dtype=np.float64) / self.time_s)

    def apply(self, readings: Readings, exposure: Exposure) -> Readings:
        return replace(
            readings,
            pos_e=readings.pos_e * self.factor(exposure.t_pos),
            neg_e=readings.neg_e * self.factor(exposure.t_neg),
        )


# --------------------------------------------------------------------------------------------
# The read-out and the output stage
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectorReadout:
    """The InGaAs photodiode reads every reading: shot, dark and read noise, pedestal, saturation
    (counted and warned about, never hidden) and ADC (:class:`~nirspi_pipe.physics.detector.Photodiode`).
    Also takes the LEDs-off reference readings and records Algorithm A1's range. The read-out
    step (:class:`ReadOut`) between the reading and the output stages."""

    detector: Photodiode

    name: ClassVar[str] = "detector"
    streams: ClassVar[tuple[int, ...]] = (2,)
    dark_readings: ClassVar[bool] = True

    def read(self, readings: Readings, exposure: Exposure) -> Output:
        det = self.detector
        rng = exposure.rng(2)
        pos_e, neg_e = readings.total_e()
        m, n_dark = exposure.m, exposure.n_dark
        signal_mean = readings.signal_mean_e
        epc = det.electrons_per_count
        y_pos, sat_pos = det.read(pos_e, rng)
        y_neg, sat_neg = det.read(neg_e, rng)
        saturated = int(sat_pos.sum() + sat_neg.sum())
        derived: dict[str, Any] = dict(
            read_noise_e=float(det.read_noise_e),
            dark_electrons=float(det.dark_electrons),
            electrons_per_count=float(epc),
            led_count=int(exposure.budget.led_count),
            noise_photons_per_pattern=float(det.noise_e(signal_mean + readings.background_e)),
        )
        if det.full_scale_e is not None:
            derived["full_scale_e"] = float(det.full_scale_e)
        if n_dark:
            bg_dark = 0.0 if readings.ambient is None else readings.ambient.dark
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
        derived.update(self._range(exposure, readings))
        return Output(
            y_pos=y_pos,
            y_neg=y_neg,
            gain=exposure.ref_e / epc,
            readings=readings,
            noise_e=float(derived["noise_photons_per_pattern"]),
            saturated=saturated,
            derived={**readings.derived, **derived},
        )

    def _range(self, exposure: Exposure, readings: Readings) -> dict[str, float]:
        """Alg. A1 for this configuration and the object's mean reflectance."""
        scene = exposure.scene
        obj = scene.mask if scene.mask.any() else scene.coverage > 0
        if not obj.any():
            return {}
        refl = float(np.clip(scene.reflectance[obj].mean(), 0.0, 1.0))
        cond = {"beta_per_m": readings.beta_per_m, **readings.conditions}
        return {"range_max_m": max_distance_m(refl, self.detector, **cond), "range_reflectance": refl}


@dataclass(frozen=True)
class GaussianNoise:
    """Idealised additive Gaussian noise on every reading (output units), of std ``noise_rel``
    times the mean noise-free half-pattern reading (the foundation's noise model)."""

    noise_rel: Annotated[float, NOISE_REL]

    name: ClassVar[str] = "gaussian_noise"
    domain: ClassVar[Literal["output"]] = "output"

    def __post_init__(self) -> None:
        check_ranges(self)

    def apply(self, output: Output, exposure: Exposure) -> Output:
        rng = exposure.rng_main if exposure.rng_main is not None else np.random.default_rng(0)
        sigma = self.noise_rel * 0.5 * float(exposure.scene.radiance.sum()) * output.gain
        y_pos = output.y_pos + rng.normal(0.0, sigma, output.y_pos.shape)
        y_neg = output.y_neg + rng.normal(0.0, sigma, output.y_neg.shape)
        noise_e = float(np.hypot(output.noise_e, sigma * (exposure.ref_e / output.gain)))
        return replace(output, y_pos=y_pos, y_neg=y_neg, noise_e=noise_e).with_derived(noise_sigma=float(sigma))


# --------------------------------------------------------------------------------------------
# The chain
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ForwardModel:
    """The forward model in its stages (module docstring), each a tuple of effects of its own
    protocol, so an effect can only stand where its type fits; the constructor also checks each
    effect's declared stage (:func:`stage_of`), a one-line :class:`ConfigError` naming the slot.

    Attributes:
        image: image effects, in order (e.g. ``budget``, ``fog``, ``rain``).
        readings: reading effects, in order (e.g. ``backscatter``, ``background``).
        readout: the read-out (the photodiode, :class:`DetectorReadout`); None: the ideal one,
            relative radiance (:func:`ideal_readout`).
        output: output effects, in order (e.g. ``gaussian_noise``).
    """

    image: tuple[ImageEffect, ...] = ()
    readings: tuple[ReadingEffect, ...] = ()
    readout: ReadOut | None = None
    output: tuple[OutputEffect, ...] = ()

    def __post_init__(self) -> None:
        for stage in STAGES:
            effects = tuple(getattr(self, stage))
            for i, effect in enumerate(effects):
                if stage_of(effect, f"{stage}.{i}") != stage:
                    raise ConfigError(f"{stage}.{i}", effect, f"an effect of the {stage} stage (domain {stage!r})")
            object.__setattr__(self, stage, effects)  # a list from a config becomes the tuple
        if self.readout is not None and not isinstance(self.readout, ReadOut):
            raise ConfigError("readout", self.readout, "a read-out with a name and read(readings, exposure)")

    @property
    def effects(self) -> tuple[Effect, ...]:
        """Every step, in the order they act (the read-out between readings and output)."""
        readout: tuple[Effect, ...] = () if self.readout is None else (self.readout,)
        return (*self.image, *self.readings, *readout, *self.output)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the steps, in the order they act (the record's ``info.source.effects``)."""
        return tuple(e.name for e in self.effects)

    @property
    def n_streams(self) -> int:
        """Number of random streams the steps declare (``streams``): the highest one plus 1."""
        return max((s + 1 for e in self.effects for s in getattr(e, "streams", ())), default=0)

    @property
    def dark_readings(self) -> bool:
        """Whether a step needs the LEDs-off reference readings (the physical detector)."""
        return any(getattr(e, "dark_readings", False) for e in self.effects)

    @property
    def budget(self) -> PhotonBudget:
        """The camera's photon budget: the illumination effect's, or the default one."""
        return next((e.budget for e in self.image if isinstance(e, Illumination)), PhotonBudget())

    def start(self, exposure: Exposure) -> ImageState:
        """The image before any effect: the scene radiance at ``ref_e`` e⁻ per unit, per pixel."""
        return ImageState(image_e=exposure.scene.radiance * exposure.ref_e)

    def run(self, exposure: Exposure) -> Output:
        """One acquisition: image effects, :func:`measure`, reading effects, read-out, output
        effects."""
        image = self.start(exposure)
        for image_effect in self.image:
            image = image_effect.apply(image, exposure)
        readings = measure(image, exposure)
        for reading_effect in self.readings:
            readings = reading_effect.apply(readings, exposure)
        output = ideal_readout(readings, exposure) if self.readout is None else self.readout.read(readings, exposure)
        for output_effect in self.output:
            output = output_effect.apply(output, exposure)
        return output

    def reference_e(self, exposure: Exposure) -> np.ndarray:
        """``(n, n)`` the noise-free, static image, e⁻ per pixel: exactly the effects that declare
        ``in_reference``. The image effects act on the scene with ``exposure`` (give it
        :meth:`Exposure.static`: no readings), the fog attenuates it steadily
        (:meth:`ImageState.steady_e`), then each reading effect adds its steady contribution
        (:meth:`ReferenceReadingEffect.reference_e`, e.g. the backscatter veil)."""
        image = self.start(exposure)
        for image_effect in self.image:
            if image_effect.in_reference:
                image = image_effect.apply(image, exposure)
        img = image.steady_e()
        for reading_effect in self.readings:
            if reading_effect.in_reference:
                img = cast(ReferenceReadingEffect, reading_effect).reference_e(img, image, exposure)
        return img


def _active(model: Any) -> bool:
    return model is not None and bool(getattr(model, "active", True))


def forward_model(
    fog: Any = None,
    illumination: Background | None = None,
    detector: Any = None,
    noise_rel: float = 0.0,
    extra: Sequence[AnyEffect] = (),
    led_droop_rel: float = 0.0,
    led_droop_time_s: float = 0.05,
) -> ForwardModel:
    """The forward model of the effects that the models enable (off effects are left out).

    Args:
        fog: a fog model (``fog=chamber|measured``; ``NoFog`` or None: clear air).
        illumination: the background light (0 kLux or None: none).
        detector: ``Photodiode`` (budget effect + read-out) or ``IdealDetector``/None.
        noise_rel: idealised Gaussian noise, relative (0: none).
        led_droop_rel, led_droop_time_s: LED power droop during the acquisition (:class:`LedDroop`;
            0: none).
        extra: further effects (plugins), each placed in the stage it declares (``domain``), in
            the order given: ``"image"`` after the fog effects, ``"readings"`` after the
            background light, ``"output"`` at the end. An effect that declares no stage, or not
            its protocol, is a :class:`ConfigError` naming ``extra.<i>``.
    """
    if detector is not None and not hasattr(detector, "physical"):
        raise ConfigError("detector", detector, "a detector from conf/detector (ideal, ingaas)")
    check_value(noise_rel, NOISE_REL)
    placed: dict[str, list[Any]] = {stage: [] for stage in STAGES}
    for i, effect in enumerate(extra):
        placed[stage_of(effect, f"extra.{i}")].append(effect)
    check_value(led_droop_rel, LED_DROOP_REL)
    physical = bool(getattr(detector, "physical", False))
    image: list[ImageEffect] = []
    readings: list[ReadingEffect] = []
    output: list[OutputEffect] = []
    if physical:
        image.append(Illumination(detector.budget))
    if _active(fog):
        image.append(FogAttenuation(fog))
        if float(getattr(fog, "fluctuation_rel", 0.0)) > 0:
            image.append(FogFluctuation(float(fog.fluctuation_rel), float(fog.fluctuation_time_s)))
        if float(getattr(fog, "trend_rel", 0.0)) != 0:
            image.append(FogTrend(float(fog.trend_rel)))
    image += placed["image"]
    if _active(fog) and float(getattr(fog, "backscatter_gain", 0.0)) > 0:
        readings.append(Backscatter(float(fog.backscatter_gain)))
    if led_droop_rel != 0:
        readings.append(LedDroop(float(led_droop_rel), float(led_droop_time_s)))
    if _active(illumination):
        assert illumination is not None
        readings.append(BackgroundLight(illumination))
        if illumination.time_varying:
            readings.append(
                BackgroundDrift(
                    illumination.drift_rel_per_s,
                    float(illumination.flicker_rel or 0.0),
                    illumination.flicker_hz,
                    illumination.wander_rel,
                    illumination.wander_time_s,
                )
            )
    readings += placed["readings"]
    if noise_rel > 0:
        output.append(GaussianNoise(float(noise_rel)))
    output += placed["output"]
    return ForwardModel(
        image=tuple(image),
        readings=tuple(readings),
        readout=DetectorReadout(detector) if physical else None,
        output=tuple(output),
    )
