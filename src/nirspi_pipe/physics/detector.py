"""Detectors: the ideal one (relative radiance, no noise) and the InGaAs photodiode with its
photon budget, shot noise, dark current, read noise, saturation and ADC.

A reading is the charge integrated during one pattern (``T_int``). The photodiode model:

1. mean photoelectrons ``μ`` (signal + background + backscatter) plus dark electrons
   ``I_dark T_int / q``;
2. Poisson shot noise on that sum (a Gaussian with the same mean and variance above 10⁷
   electrons, where they are indistinguishable and numpy's Poisson sampler gets slow);
3. Gaussian read noise ``read_noise_e`` (the paper's "noise floor": amplifier, kTC and ADC noise
   lumped; its default is calibrated on Table 2, see
   :func:`nirspi_pipe.physics.range_model.calibrate`);
4. an electronic pedestal ``offset_e`` (so that read noise on a dark reading is not clipped at
   zero; it cancels in every difference), then saturation at the full-scale charge ``C_eq · V_fs / q`` (Table 1: C_eq = 19 fF; 1 V swing
   → 1.19·10⁵ e⁻), counted, never hidden;
5. an ADC of ``adc_bits`` over that full scale (``null``: no quantisation).

Readings are returned in ADC counts (DN); ``electrons_per_count`` converts back.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.ranges import Range, check_ranges

__all__ = ["IdealDetector", "Photodiode", "sample_electrons", "digitize", "ELEMENTARY_CHARGE"]

ELEMENTARY_CHARGE = 1.602176634e-19  # C
_POISSON_MAX = 1e7


def sample_electrons(
    mean_e: np.ndarray,
    rng: np.random.Generator,
    shot: bool,
    read_noise_e: float,
    poisson_max: float = _POISSON_MAX,
) -> np.ndarray:
    """Random photoelectron counts around ``mean_e`` (e⁻, ≥ 0): Poisson shot noise (when
    ``shot``; a Gaussian of the same mean and variance above ``poisson_max`` e⁻) and Gaussian
    read noise of ``read_noise_e`` e⁻ rms. Never NaN for finite input."""
    mean = np.clip(np.nan_to_num(np.asarray(mean_e, dtype=np.float64), nan=0.0, posinf=1e300), 0.0, 1e300)
    out = mean
    if shot:
        small = mean <= poisson_max
        out = np.empty_like(mean)
        out[small] = rng.poisson(mean[small])
        big = ~small
        if big.any():
            out[big] = mean[big] + np.sqrt(mean[big]) * rng.standard_normal(int(big.sum()))
    if read_noise_e > 0:
        out = out + rng.normal(0.0, read_noise_e, mean.shape)
    return out


def digitize(
    electrons: np.ndarray, full_scale_e: float | None, bits: int | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """Clip at ``[0, full_scale_e]`` and quantise to ``bits``.

    Returns ``(counts, saturated, electrons_per_count)``: counts are floats in DN; ``saturated``
    flags readings at or above full scale. Without a full scale there is no clipping at the top
    (but charge is still ≥ 0); without bits, counts are electrons (1 e⁻/DN).
    """
    e = np.maximum(electrons, 0.0)
    if full_scale_e is None:
        return e, np.zeros(e.shape, dtype=bool), 1.0
    saturated = e >= full_scale_e
    e = np.minimum(e, full_scale_e)
    if bits is None:
        return e, saturated, 1.0
    levels = 2 ** int(bits)
    step = full_scale_e / levels
    counts = np.minimum(np.floor(e / step), levels - 1)
    return counts, saturated, step


@dataclass(frozen=True)
class IdealDetector:
    """``detector=ideal``: noise-free, unlimited, in relative-radiance units (gain 1).

    The reading of a pattern is ``Σ pattern ⊙ radiance`` exactly, with no distance fall-off across
    the object, no noise, no saturation and no quantisation. Effects that are configured (fog,
    background light) still act; the default :class:`PhotonBudget` converts them into these
    units. With ``fog=none`` and ``illumination=none`` the reconstruction equals the scene
    radiance to rounding.
    """

    physical = False
    budget = None


@dataclass(frozen=True)
class Photodiode:
    """``detector=ingaas``: InGaAs photodiode (FGA015-like) with the Table 1 photon budget.

    Attributes:
        budget: the photon budget (Eqs. 10–11).
        shot_noise: Poisson photon shot noise on signal, background and dark charge.
        dark_current_na: dark current, nA. Default 0.0066 nA: the FGA015's 0.5 nA (typical, over
            its Ø150 µm area) scaled to Table 1's 235 µm² photosensitive area.
        read_noise_e: Gaussian noise floor per reading, e⁻ rms (calibrated, see module doc).
        c_eq_ff: equivalent capacitance C_eq, fF (Table 1: 19 fF).
        full_scale_v: voltage swing at full scale, V; null: no saturation.
        adc_bits: ADC resolution in bits; null: no quantisation.
        offset_e: electronic pedestal added before the ADC, e⁻ (within the full scale).
    """

    budget: PhotonBudget = field(default_factory=PhotonBudget)
    shot_noise: bool = True
    dark_current_na: Annotated[float, Range(0.0, 1e6, "a current in nA")] = 0.0066
    read_noise_e: Annotated[float, Range(0.0, 1e9, "a noise in e⁻ rms")] = 376.66
    c_eq_ff: Annotated[float, Range(0.0, 1e9, "a capacitance in fF", lo_open=True)] = 19.0
    full_scale_v: Annotated[float | None, Range(0.0, 1e3, "a voltage in V", lo_open=True)] = 1.0
    adc_bits: Annotated[int | None, Range(1, 32, "an integer", integer=True)] = 16
    offset_e: Annotated[float, Range(0.0, 1e12, "a pedestal in e⁻")] = 2000.0

    physical = True

    def __post_init__(self) -> None:
        if isinstance(self.budget, Mapping):  # a config (``_recursive_: false``): build it here
            params = {str(k): v for k, v in self.budget.items() if not str(k).startswith("_")}
            try:
                object.__setattr__(self, "budget", PhotonBudget(**params))
            except ConfigError as exc:
                raise ConfigError(f"budget.{exc.key}", exc.value, exc.allowed) from None
            except TypeError as exc:
                raise ConfigError("budget", params, f"PhotonBudget keys ({exc})") from None
        if not isinstance(self.budget, PhotonBudget):
            raise ConfigError("budget", self.budget, "a PhotonBudget (Eqs. 10–11)")
        check_ranges(self)

    @property
    def dark_electrons(self) -> float:
        """Mean dark charge per integration, e⁻."""
        return self.dark_current_na * 1e-9 * self.budget.t_int_us * 1e-6 / ELEMENTARY_CHARGE

    @property
    def full_scale_e(self) -> float | None:
        """Saturation charge ``C_eq V_fs / q``, e⁻ (None: unlimited)."""
        if self.full_scale_v is None:
            return None
        return self.c_eq_ff * 1e-15 * self.full_scale_v / ELEMENTARY_CHARGE

    @property
    def electrons_per_count(self) -> float:
        """e⁻ per ADC count (1 without an ADC)."""
        fs = self.full_scale_e
        if fs is None or self.adc_bits is None:
            return 1.0
        return fs / 2 ** int(self.adc_bits)

    def noise_e(self, mean_e: float | np.ndarray) -> np.ndarray:
        """Expected noise (e⁻ rms) of a reading whose mean photo-charge is ``mean_e``."""
        shot = (np.asarray(mean_e, dtype=np.float64) + self.dark_electrons) if self.shot_noise else 0.0
        q = self.electrons_per_count**2 / 12.0 if self.adc_bits is not None and self.full_scale_v is not None else 0.0
        return np.sqrt(self.read_noise_e**2 + shot + q)

    def read(self, mean_e: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Readings in DN of photo-charges ``mean_e`` (e⁻), and the saturated flags."""
        e = sample_electrons(
            np.asarray(mean_e, dtype=np.float64) + self.dark_electrons, rng, self.shot_noise, self.read_noise_e
        )
        counts, saturated, _ = digitize(e + self.offset_e, self.full_scale_e, self.adc_bits)
        return counts, saturated
