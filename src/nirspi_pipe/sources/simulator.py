"""Source ``simulator``: the NIR-SPI camera in the fog chamber (paper §§3–5, Eqs. 5–12).

The simulator runs the forward model that the config enables, and nothing else, in its typed
stages: image effects, the measurement, reading effects, the read-out, output effects
(:mod:`nirspi_pipe.physics.effects`; docs/architecture.md draws them). The runner builds the
:class:`~nirspi_pipe.physics.effects.ForwardModel` from the ``fog``, ``illumination`` and
``detector`` groups (``source.effects`` in conf/source/simulator.yaml, Hydra's recursive
instantiation) and hands it to :class:`Simulator`; the simulator never builds an effect.
``fog=none``, ``illumination=none`` (0 kLux) and ``detector=ideal`` put nothing in it: no Mie
call, no fog array, no noise draw. With an empty model the readings are the split Hadamard
measurements of the scene radiance and the reconstruction equals it to rounding. The reference
the normalised metrics score against (``Acquisition.reference``) is formed by exactly the effects
that declare ``in_reference`` (:meth:`Simulator.reference_image`).

Split convention: each ±1 pattern ``P_k`` is shown as ``(1 + P_k)/2`` then ``(1 − P_k)/2``, one
pattern period apart (``1/pattern_rate_hz``), so a changing background does not cancel exactly
in their difference. When an effect needs them (the physical detector), ``dark_readings``
LEDs-off readings come first (the background/dark reference used for the measured signal).

Units: readings are ADC counts for a physical detector (``gain`` = counts per unit relative
radiance per pixel at the scene's nominal distance in clear air), relative radiance for the
ideal one (``gain = 1``). ``Acquisition.coefficients()`` is therefore always relative radiance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.effects import ForwardModel
from nirspi_pipe.physics.stagetypes import Exposure
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.types import Acquisition, Medium, Scene

__all__ = ["Simulator"]

#: ``snr_db`` is clipped to ±this (noise-free or signal-free readings), so records stay finite.
SNR_DB_LIMIT = 200.0


def _fog_path_m(medium: Any, distance_m: float) -> float:
    """Fog path to the nominal distance, m: ``min(distance, extent)`` (0 in clear air)."""
    if medium is None:
        return 0.0
    return float(min(float(distance_m), float(medium.extent_m)))


def _spawn(rng: np.random.Generator, k: int) -> list[np.random.Generator]:
    """``k`` independent child generators (one per random stream) without drawing from ``rng``,
    so an effect switched on does not change another's noise."""
    if hasattr(rng, "spawn"):  # numpy >= 1.25
        return rng.spawn(k)
    seq: Any = rng.bit_generator.seed_seq  # a SeedSequence for default_rng generators
    return [np.random.default_rng(s) for s in seq.spawn(k)]


#: Pattern rates the simulator accepts, Hz. Assumed: the paper's device shows 1000 patterns/s;
#: one pattern in 11.6 days (1e-6 Hz) and 1e12 per second (beyond any DMD or LED driver, tens
#: of kHz to MHz) bracket every rate a user can mean. At 1e-300 Hz the time stamps (1e300 s and
#: more) overflowed float64 in the drift's squares (measured, illumination.drift_rel_per_s=10).
PATTERN_RATE_HZ = (1e-6, 1e12)


@dataclass(frozen=True)
class Simulator:
    """Simulated single-pixel camera: the forward model ``effects`` applied to the scene.

    Attributes:
        effects: the forward model in its typed stages (:class:`~nirspi_pipe.physics.effects.ForwardModel`;
            :func:`~nirspi_pipe.physics.effects.forward_model` builds it from the fog, illumination
            and detector models).
        pattern_rate_hz: patterns shown per second; each ±1 measurement takes two.
        dark_readings: LEDs-off reference readings taken before the patterns when a step of the
            model asks for them (the physical detector).
    """

    # not a schema key: the simulator option sets it (source.effects: forward_model(...))
    effects: ForwardModel = field(default_factory=ForwardModel, metadata={"config": False})
    pattern_rate_hz: Annotated[float, Range(*PATTERN_RATE_HZ, "a rate in Hz")] = 1000.0
    dark_readings: Annotated[int, Range(0, 100000, "an integer", integer=True)] = 16

    needs_scene: ClassVar[bool] = True

    def __post_init__(self) -> None:
        check_ranges(self)
        if not isinstance(self.effects, ForwardModel):
            raise ConfigError(
                "effects", self.effects, "a forward model (forward_model(...), conf/source/simulator.yaml)"
            )

    @property
    def effect_names(self) -> tuple[str, ...]:
        """Names of the steps of the model, in the order they act."""
        return self.effects.names

    @property
    def budget(self) -> PhotonBudget:
        """The camera's photon budget: the illumination effect's, or the default one."""
        return self.effects.budget

    def reference_image(self, scene: Scene) -> np.ndarray:
        """``(n, n)`` the noise-free, static image this camera forms of ``scene``, relative radiance.

        Exactly the effects that declare ``in_reference = True`` form it
        (:meth:`~nirspi_pipe.physics.effects.ForwardModel.reference_e`): the image effects (the
        1/r² fall-off of the photon budget, the fog's round-trip transmission, a plugin's rain or
        device optics) act on the scene radiance, and the backscatter veil (Eq. 12) is added per
        pixel; effects that change during the acquisition (fog fluctuation, background drift, LED
        droop, …), the read-out and noise do not. Steady background light cancels in the split
        difference and does not appear. Divided by the clear-air gain at the nominal distance, as
        the solver's image is. Works at any resolution (the metrics render the scene again on an
        upscaled grid).
        """
        exposure = Exposure.static(scene, self.budget)
        return np.asarray(self.effects.reference_e(exposure) / exposure.ref_e, dtype=np.float64)

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition:
        """Measure ``scene`` with the patterns ``indices``, in that order (see module docstring)."""
        if scene is None:
            raise NirspiError("source=simulator needs a scene")
        if scene.radiance.shape != (n, n):
            raise NirspiError(f"scene rendered at {scene.radiance.shape}, patterns are {n}x{n}")
        idx = np.asarray(indices, dtype=np.int64)
        m = idx.size
        model = self.effects
        n_dark = int(self.dark_readings) if model.dark_readings else 0
        period = 1.0 / self.pattern_rate_hz
        t_pos = (n_dark + 2.0 * np.arange(m)) * period
        n_streams = model.n_streams
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
        output = model.run(exposure)
        readings = output.readings
        beta = readings.beta_per_m
        signal_mean = readings.signal_mean_e
        derived: dict[str, Any] = {
            "background_irradiance_w_m2": 0.0,
            "noise_sigma": 0.0,
            **output.derived,
            "beta_per_m": beta,
            # Eq. (7) over the fog's path to the nominal distance: min(distance, extent), as the
            # fog effect fills each ray (physics/effects.py); clear air has no medium
            "transmittance_roundtrip": float(np.exp(-2.0 * beta * _fog_path_m(readings.medium, scene.distance_m))),
            "background_photons_per_pattern": readings.background_e,
            "signal_photons_per_pattern": signal_mean,
            "saturated_patterns": output.saturated,
            "saturated_fraction": output.saturated / max(exposure.readings, 1),
        }
        noise_e = output.noise_e
        if noise_e > 0 and signal_mean > 0:
            snr_db = 20.0 * np.log10(signal_mean / noise_e)
        else:
            snr_db = SNR_DB_LIMIT if signal_mean > 0 else -SNR_DB_LIMIT
        derived["snr_db"] = float(np.clip(snr_db, -SNR_DB_LIMIT, SNR_DB_LIMIT))
        info = {"patterns_measured": m, "patterns_shown": exposure.readings, "effects": ",".join(self.effect_names)}
        return Acquisition(
            n=n,
            indices=idx,
            y_pos=np.asarray(output.y_pos, dtype=np.float64),
            y_neg=np.asarray(output.y_neg, dtype=np.float64),
            gain=float(output.gain),
            truth=scene,
            timestamps_s=t_pos,
            medium=Medium(beta, float(derived["background_irradiance_w_m2"])),
            derived=derived,
            info=info,
            reference=self.reference_image(scene),
        )
