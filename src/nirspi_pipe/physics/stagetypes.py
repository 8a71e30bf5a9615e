"""The forward model's typed stages: what flows between them, and what an effect of each is.

The simulated acquisition runs in five stages, and each hands the next a different frozen
dataclass, so the order is a matter of types (an effect written for one stage does not type-check
in another, and :func:`stage_of` refuses it at build time with a one-line
:class:`~nirspi_pipe.errors.ConfigError`)::

    ImageState ──image effects──► ImageState ─measure─► Readings ──reading effects──► Readings
        ─read-out─► Output ──output effects──► Output

1. **image effects** (:class:`ImageEffect`, ``domain = "image"``) change the per-pixel image:
   :class:`ImageState` (``image_e``, e⁻ per pixel from the active light, and the fog between
   camera and object, :class:`FogPath`, with its round-trip optical depth and, when the fog
   changes during the acquisition, its per-reading scale);
2. **measurement** (:func:`measure`): the split Hadamard patterns measure ``image_e ⊙ e^{−τ}``
   (Eq. 1), giving :class:`Readings`;
3. **reading effects** (:class:`ReadingEffect`, ``domain = "readings"``) change the charge of
   every reading: ``pos_e``/``neg_e`` (e⁻ per reading of the split pattern pair, active light)
   and the ambient charge (:class:`AmbientCharge`);
4. **read-out** (a :class:`ReadOut`, e.g. the photodiode; or :func:`ideal_readout`, relative
   radiance) turns charge into detector units: :class:`Output`;
5. **output effects** (:class:`OutputEffect`, ``domain = "output"``) change ``y_pos``/``y_neg``
   in detector units.

"Belongs in the noise-free reference" is part of the protocol: image and reading effects declare
``in_reference: bool``. The reference the normalised metrics score against
(``Acquisition.reference``, :meth:`nirspi_pipe.physics.effects.ForwardModel.reference_e`) is the
static image formed by exactly the effects with ``in_reference = True``: the image effects applied
to the scene with a static exposure (no readings), the attenuation ``e^{−τ}`` of the fog, then the
per-pixel contribution :meth:`ReferenceReadingEffect.reference_e` of the reading effects. Effects
that change during the acquisition, background light (it cancels in the split difference), noise
and the read-out are not in it; output effects never are.

Plugin authors import these names from here (docs/plugins.md §7). The chain that runs the
stages, :class:`~nirspi_pipe.physics.effects.ForwardModel`, and the built-in effects are in
:mod:`nirspi_pipe.physics.effects`; the split measurement itself in
:mod:`nirspi_pipe.physics.splitmeasure`. (This module was ``physics/forward.py``; issue 42 item 5.)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.splitmeasure import modulated_split, split_measure

__all__ = [
    "Exposure",
    "FogPath",
    "ImageState",
    "AmbientCharge",
    "Readings",
    "Output",
    "Effect",
    "ImageEffect",
    "ReadingEffect",
    "ReferenceReadingEffect",
    "ReadOut",
    "OutputEffect",
    "AnyEffect",
    "STAGES",
    "stage_of",
    "measure",
    "ideal_readout",
]


# --------------------------------------------------------------------------------------------
# What is fixed during one acquisition
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

    @classmethod
    def static(cls, scene: Any, budget: PhotonBudget) -> Exposure:
        """The exposure of the noise-free reference: the scene at its own resolution, no
        readings (``m = 0``, no times), no random streams."""
        empty = np.zeros(0)
        n = int(scene.radiance.shape[0])
        return cls(scene, np.zeros(0, dtype=np.int64), n, empty, empty, empty, budget)

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


# --------------------------------------------------------------------------------------------
# The hand-offs between the stages
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FogPath:
    """The fog between camera and object, as the fog effect set it up.

    Attributes:
        beta_per_m: extinction coefficient β, 1/m.
        path_m: ``(n, n)`` fog path along each ray, ``min(range, extent)``, m.
        extent_m: fog path length of the chamber, m.
        albedo: single-scattering albedo ``Q_sca/Q_ext``.
        optical_depth: ``(n, n)`` round-trip optical depth ``τ = 2 β ℓ`` per pixel (Eq. 6), 0
            off the object.
        fluctuation: ``(m,)`` factors of τ for the positive and the negative half readings when
            the fog density changes during the acquisition (``β(t) = β f(t)``); None while the fog
            is steady.
    """

    beta_per_m: float
    path_m: np.ndarray
    extent_m: float
    albedo: float
    optical_depth: np.ndarray
    fluctuation: tuple[np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class ImageState:
    """Image domain: the per-pixel image before any pattern measures it.

    Attributes:
        image_e: ``(n, n)`` e⁻ per pixel from the active light, before the fog's attenuation.
        medium: the fog between camera and object (None: clear air).
        derived: physical quantities for the record (``Acquisition.derived``).
        conditions: keyword conditions of Algorithm A1 (:func:`range_model.max_distance_m`).
    """

    image_e: np.ndarray
    medium: FogPath | None = None
    derived: Mapping[str, Any] = field(default_factory=dict)
    conditions: Mapping[str, float] = field(default_factory=dict)

    def with_derived(self, **values: Any) -> ImageState:
        """The same state with more quantities for the record."""
        return replace(self, derived={**self.derived, **values})

    def steady_e(self) -> np.ndarray:
        """``(n, n)`` the image the patterns see with the fog steady: ``image_e ⊙ e^{−τ}``, e⁻."""
        if self.medium is None:
            return self.image_e
        return self.image_e * np.exp(-self.medium.optical_depth)


@dataclass(frozen=True)
class AmbientCharge:
    """Charge from the ambient light (Eqs. 7, 10–11), e⁻ per reading.

    Attributes:
        level_e: the steady level, e⁻ per reading.
        pos, neg: on the positive/negative half readings (``level_e``, or ``(m,)`` when it drifts).
        dark: on the LEDs-off reference readings (``level_e``, or ``(n_dark,)``).
    """

    level_e: float
    pos: float | np.ndarray
    neg: float | np.ndarray
    dark: float | np.ndarray

    @classmethod
    def steady(cls, level_e: float) -> AmbientCharge:
        """The same charge ``level_e`` on every reading."""
        return cls(level_e, level_e, level_e, level_e)


@dataclass(frozen=True)
class Readings:
    """Measurement domain: the charge of every reading of the split pattern pairs, before read-out.

    Attributes:
        pos_e, neg_e: ``(m,)`` e⁻ from the active light on the positive/negative half readings.
        medium: the fog the image went through (None: clear air); read by the backscatter and
            the background light.
        ambient: the background light's charge (None: no ambient light).
        derived, conditions: as in :class:`ImageState`, carried on.
    """

    pos_e: np.ndarray
    neg_e: np.ndarray
    medium: FogPath | None = None
    ambient: AmbientCharge | None = None
    derived: Mapping[str, Any] = field(default_factory=dict)
    conditions: Mapping[str, float] = field(default_factory=dict)

    def with_derived(self, **values: Any) -> Readings:
        """The same readings with more quantities for the record."""
        return replace(self, derived={**self.derived, **values})

    @property
    def beta_per_m(self) -> float:
        """β of the medium, 1/m (0 in clear air)."""
        return self.medium.beta_per_m if self.medium is not None else 0.0

    @property
    def background_e(self) -> float:
        """Steady ambient charge per reading, e⁻ (0 without background light)."""
        return self.ambient.level_e if self.ambient is not None else 0.0

    @property
    def signal_mean_e(self) -> float:
        """Mean active-light charge per reading (before background), e⁻."""
        if self.pos_e.size == 0:
            return 0.0
        return float(0.5 * (self.pos_e.mean() + self.neg_e.mean()))

    def total_e(self) -> tuple[np.ndarray, np.ndarray]:
        """Charge per reading, active light plus ambient, e⁻."""
        if self.ambient is None:
            return self.pos_e, self.neg_e
        return self.pos_e + self.ambient.pos, self.neg_e + self.ambient.neg


@dataclass(frozen=True)
class Output:
    """Output domain: the readings in detector units.

    Attributes:
        y_pos, y_neg: ``(m,)`` readings in detector units (ADC counts, or relative radiance for
            the ideal read-out).
        gain: detector units per unit relative radiance per pixel at the scene's nominal distance
            in clear air (``Acquisition.gain``).
        readings: the charge that was read out.
        noise_e: noise per reading referred to the input, e⁻ (0: noise-free).
        saturated: number of readings that saturated the detector.
        derived: as in :class:`ImageState`, carried on.
    """

    y_pos: np.ndarray
    y_neg: np.ndarray
    gain: float
    readings: Readings
    noise_e: float = 0.0
    saturated: int = 0
    derived: Mapping[str, Any] = field(default_factory=dict)

    def with_derived(self, **values: Any) -> Output:
        """The same output with more quantities for the record."""
        return replace(self, derived={**self.derived, **values})


# --------------------------------------------------------------------------------------------
# The protocols of the stages
# --------------------------------------------------------------------------------------------


@runtime_checkable
class Effect(Protocol):
    """What every step of the forward model has: a ``name``, listed in chain order in the record
    (``info.source.effects``). ``name`` may be a class attribute (``name: ClassVar[str] = "rain"``)
    or a field. Optional: ``streams: tuple[int, ...]`` (the random streams it draws from,
    :meth:`Exposure.rng`) and ``dark_readings: bool`` (it needs LEDs-off reference readings)."""

    @property
    def name(self) -> str: ...


@runtime_checkable
class ImageEffect(Effect, Protocol):
    """An effect on the per-pixel image, before anything is measured (fog, rain, fall-off).

    ``domain = "image"`` declares the stage (``domain: ClassVar[Literal["image"]] = "image"``).
    ``in_reference``: True when the effect is part of the static, noise-free image the metrics
    score against; it is then applied to the scene once more with :meth:`Exposure.static` (no
    readings), so it must not need reading times or random streams there."""

    @property
    def domain(self) -> Literal["image"]: ...

    @property
    def in_reference(self) -> bool: ...

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState: ...


@runtime_checkable
class ReadingEffect(Effect, Protocol):
    """An effect on the charge of every reading (veil, LED droop, background light, drift).

    ``domain = "readings"``. ``in_reference``: True when its steady contribution is part of the
    reference image; it must then also be a :class:`ReferenceReadingEffect`."""

    @property
    def domain(self) -> Literal["readings"]: ...

    @property
    def in_reference(self) -> bool: ...

    def apply(self, readings: Readings, exposure: Exposure) -> Readings: ...


@runtime_checkable
class ReferenceReadingEffect(ReadingEffect, Protocol):
    """A reading effect that is in the reference, and says what it does to it per pixel."""

    def reference_e(self, image_e: np.ndarray, image: ImageState, exposure: Exposure) -> np.ndarray:
        """``(n, n)`` the static reference image (e⁻ per pixel, ``image_e``) with this effect's
        steady contribution; ``image`` is the image state the reference was formed from."""
        ...


@runtime_checkable
class ReadOut(Effect, Protocol):
    """The read-out: charge per reading to detector units (the photodiode). Without one the
    readings are relative radiance (:func:`ideal_readout`)."""

    def read(self, readings: Readings, exposure: Exposure) -> Output: ...


@runtime_checkable
class OutputEffect(Effect, Protocol):
    """An effect on the readings in detector units (idealised Gaussian noise). ``domain =
    "output"``. Never part of the reference (it acts on detector units)."""

    @property
    def domain(self) -> Literal["output"]: ...

    def apply(self, output: Output, exposure: Exposure) -> Output: ...


#: An effect of any stage (what ``forward_model(extra=...)`` takes).
AnyEffect = ImageEffect | ReadingEffect | OutputEffect

#: The stages an effect may declare (``domain``), with their protocols, in chain order.
STAGES: Mapping[str, type] = {"image": ImageEffect, "readings": ReadingEffect, "output": OutputEffect}

_STAGE_KINDS = (
    "an effect with a name and its stage: domain 'image' (ImageEffect: apply(ImageState, Exposure)), "
    "'readings' (ReadingEffect: apply(Readings, Exposure)) or 'output' (OutputEffect: apply(Output, "
    "Exposure)), and in_reference true or false for image and readings (docs/plugins.md §7)"
)


def stage_of(effect: Any, key: str) -> str:
    """The stage ``effect`` declares (``"image"``, ``"readings"`` or ``"output"``), checked against
    its protocol; a :class:`ConfigError` naming ``key`` and the allowed stage kinds otherwise.
    Called when the chain is built, so a misplaced or undeclared effect never runs."""
    domain = getattr(effect, "domain", None)
    if not isinstance(domain, str) or domain not in STAGES or not isinstance(effect, STAGES[domain]):
        raise ConfigError(key, effect, _STAGE_KINDS)
    in_ref = getattr(effect, "in_reference", False)
    if domain != "output" and not isinstance(in_ref, bool):
        raise ConfigError(key, effect, _STAGE_KINDS)
    if domain == "readings" and in_ref and not isinstance(effect, ReferenceReadingEffect):
        raise ConfigError(
            key, effect, "a readings effect with in_reference true that defines reference_e(image_e, image, exposure)"
        )
    if domain == "output" and in_ref is not False:
        raise ConfigError(key, effect, "an output effect without in_reference (output effects are never in it)")
    return domain


# --------------------------------------------------------------------------------------------
# The steps between the stages
# --------------------------------------------------------------------------------------------


def measure(image: ImageState, exposure: Exposure) -> Readings:
    """Image → readings: the split patterns ``exposure.indices`` measure the attenuated image
    ``image_e ⊙ e^{−τ}`` (Eqs. 1, 6), with a per-reading scale of ``τ`` when the fog changes
    during the acquisition (:func:`modulated_split`). e⁻ per reading."""
    idx = exposure.indices
    med = image.medium
    if med is None:
        pos, neg = split_measure(image.image_e, idx)
    elif med.fluctuation is None:
        pos, neg = split_measure(image.image_e * np.exp(-med.optical_depth), idx)
    else:
        pos, neg = modulated_split(image.image_e, med.optical_depth, med.fluctuation[0], med.fluctuation[1], idx)
    return Readings(pos_e=pos, neg_e=neg, medium=med, derived=image.derived, conditions=image.conditions)


def ideal_readout(readings: Readings, exposure: Exposure) -> Output:
    """Readings → output without a detector: charge divided by :attr:`Exposure.ref_e`, i.e.
    relative radiance, gain 1, no noise."""
    pos, neg = readings.total_e()
    ref = exposure.ref_e
    return Output(y_pos=pos / ref, y_neg=neg / ref, gain=1.0, readings=readings, derived=readings.derived)
