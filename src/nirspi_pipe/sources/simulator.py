"""Source ``simulator``: the NIR-SPI camera in the fog chamber (paper §§3–5, Eqs. 5–12).

The simulator is the ordered chain of the physical effects that the config enables, and of
nothing else (:mod:`nirspi_pipe.physics.effects`; docs/architecture.md draws the chain). The
runner builds the chain from the ``fog``, ``illumination`` and ``detector`` groups
(``source.effects`` in conf/source/simulator.yaml, Hydra's recursive instantiation) and hands it
to :class:`Simulator`; the simulator never builds an effect. ``fog=none``, ``illumination=none``
(0 kLux) and ``detector=ideal`` put nothing in the chain: no Mie call, no fog array, no noise
draw. With an empty chain the readings are the split Hadamard measurements of the scene radiance
and the reconstruction equals it to rounding.

Split convention: each ±1 pattern ``P_k`` is shown as ``(1 + P_k)/2`` then ``(1 − P_k)/2``, one
pattern period apart (``1/pattern_rate_hz``), so a changing background does not cancel exactly
in their difference. When an effect needs them (the physical detector), ``dark_readings``
LEDs-off readings come first (the background/dark reference used for the measured signal).

Units: readings are ADC counts for a physical detector (``gain`` = counts per unit relative
radiance per pixel at the scene's nominal distance in clear air), relative radiance for the
ideal one (``gain = 1``). ``Acquisition.coefficients()`` is therefore always relative radiance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.effects import (
    Backscatter,
    Effect,
    Exposure,
    Illumination,
    Signal,
    modulated_split,
    split_measure,
)
from nirspi_pipe.types import Acquisition, Medium, Scene

__all__ = ["Simulator", "split_measure", "modulated_split"]

#: ``snr_db`` is clipped to ±this (noise-free or signal-free readings), so records stay finite.
SNR_DB_LIMIT = 200.0


def _spawn(rng: np.random.Generator, k: int) -> list[np.random.Generator]:
    """``k`` independent child generators (one per random stream) without drawing from ``rng``,
    so an effect switched on does not change another's noise."""
    if hasattr(rng, "spawn"):  # numpy >= 1.25
        return rng.spawn(k)
    seq: Any = rng.bit_generator.seed_seq  # a SeedSequence for default_rng generators
    return [np.random.default_rng(s) for s in seq.spawn(k)]


@dataclass(frozen=True)
class Simulator:
    """Simulated single-pixel camera: the ordered chain ``effects`` applied to the scene.

    Attributes:
        effects: the chain, in the order the effects act (:func:`~nirspi_pipe.physics.effects.forward_model`
            builds it from the fog, illumination and detector models).
        pattern_rate_hz: patterns shown per second; each ±1 measurement takes two.
        dark_readings: LEDs-off reference readings taken before the patterns when an effect of
            the chain asks for them (the physical detector).
    """

    effects: tuple[Effect, ...] = ()
    pattern_rate_hz: float = 1000.0
    dark_readings: int = 16

    needs_scene: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not np.isfinite(self.pattern_rate_hz) or not self.pattern_rate_hz > 0:
            raise ConfigError("pattern_rate_hz", self.pattern_rate_hz, "a rate in Hz > 0")
        if int(self.dark_readings) != self.dark_readings or not 0 <= self.dark_readings <= 100000:
            raise ConfigError("dark_readings", self.dark_readings, "an integer from 0 to 100000")
        chain = tuple(self.effects)
        for effect in chain:
            if not isinstance(effect, Effect):
                raise ConfigError("effects", effect, "effects with a name and apply(signal, exposure)")
        object.__setattr__(self, "effects", chain)  # a list from a config becomes the tuple

    @property
    def effect_names(self) -> tuple[str, ...]:
        """Names of the effects of the chain, in the order they act."""
        return tuple(e.name for e in self.effects)

    @property
    def budget(self) -> PhotonBudget:
        """The camera's photon budget: the illumination effect's, or the default one."""
        return next((e.budget for e in self.effects if isinstance(e, Illumination)), PhotonBudget())

    def reference_image(self, scene: Scene) -> np.ndarray:
        """``(n, n)`` the noise-free, static image this camera forms of ``scene``, relative radiance.

        The image-domain effects of the chain that declare ``reference = True`` (the 1/r²
        fall-off of the photon budget, the fog's round-trip transmission, the device optics) act
        on the scene radiance, and the backscatter veil (Eq. 12) is added per pixel; effects that
        change during the acquisition (fog fluctuation, background drift, LED droop, …) and noise
        do not. Steady background light cancels in the split difference and does not appear.
        Divided by the clear-air gain at the nominal distance, as the solver's image is. Works at
        any resolution (the metrics render the scene again on an upscaled grid).
        """
        n = int(scene.radiance.shape[0])
        empty = np.zeros(0)
        exposure = Exposure(
            scene=scene,
            indices=np.zeros(0, dtype=np.int64),
            n=n,
            t_pos=empty,
            t_neg=empty,
            t_dark=empty,
            budget=self.budget,
        )
        signal = Signal(image_e=scene.radiance * exposure.ref_e)
        veil = None
        for effect in self.effects:
            if isinstance(effect, Backscatter) and signal.medium is not None:
                veil = effect.veil_e(signal.medium, exposure)
            elif getattr(effect, "reference", False):
                signal = effect.apply(signal, exposure)
        img = signal.image_e if signal.optical_depth is None else signal.image_e * np.exp(-signal.optical_depth)
        if veil is not None:
            img = img + veil
        return np.asarray(img / exposure.ref_e, dtype=np.float64)

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition:
        """Measure ``scene`` with the patterns ``indices``, in that order (see module docstring)."""
        if scene is None:
            raise NirspiError("source=simulator needs a scene")
        if scene.radiance.shape != (n, n):
            raise NirspiError(f"scene rendered at {scene.radiance.shape}, patterns are {n}x{n}")
        idx = np.asarray(indices, dtype=np.int64)
        m = idx.size
        n_dark = int(self.dark_readings) if any(getattr(e, "dark_readings", False) for e in self.effects) else 0
        period = 1.0 / self.pattern_rate_hz
        t_pos = (n_dark + 2.0 * np.arange(m)) * period
        n_streams = max((s + 1 for e in self.effects for s in getattr(e, "streams", ())), default=0)
        exposure = Exposure(
            scene=scene,
            indices=idx,
            n=n,
            t_pos=t_pos,
            t_neg=t_pos + period,
            t_dark=np.arange(n_dark) * period,
            budget=self.budget,
            rngs=tuple(_spawn(rng, max(n_streams, 3))) if n_streams else (),
            rng_main=rng,
        )
        signal = Signal(image_e=scene.radiance * exposure.ref_e)
        for effect in self.effects:
            signal = effect.apply(signal, exposure)
        signal = signal.read_out(exposure)
        assert signal.y_pos is not None and signal.y_neg is not None
        beta = signal.beta_per_m
        signal_mean = signal.signal_mean_e
        derived: dict[str, Any] = {
            "background_irradiance_w_m2": 0.0,
            "noise_sigma": 0.0,
            **signal.derived,
            "beta_per_m": beta,
            "transmittance_roundtrip": float(np.exp(-2.0 * beta * float(scene.distance_m))),
            "background_photons_per_pattern": signal.background_e,
            "signal_photons_per_pattern": signal_mean,
            "saturated_patterns": signal.saturated,
            "saturated_fraction": signal.saturated / max(exposure.readings, 1),
        }
        noise_e = signal.noise_e
        if noise_e > 0 and signal_mean > 0:
            snr_db = 20.0 * np.log10(signal_mean / noise_e)
        else:
            snr_db = SNR_DB_LIMIT if signal_mean > 0 else -SNR_DB_LIMIT
        derived["snr_db"] = float(np.clip(snr_db, -SNR_DB_LIMIT, SNR_DB_LIMIT))
        info = {"patterns_measured": m, "patterns_shown": exposure.readings, "effects": ",".join(self.effect_names)}
        return Acquisition(
            n=n,
            indices=idx,
            y_pos=np.asarray(signal.y_pos, dtype=np.float64),
            y_neg=np.asarray(signal.y_neg, dtype=np.float64),
            gain=float(signal.gain),
            truth=scene,
            timestamps_s=t_pos,
            medium=Medium(beta, float(derived["background_irradiance_w_m2"])),
            derived=derived,
            info=info,
            reference=self.reference_image(scene),
        )
