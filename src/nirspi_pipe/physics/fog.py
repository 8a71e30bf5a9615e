"""Fog: droplet size (Eq. 5), Mie efficiencies, extinction (Eq. 6), Beer–Lambert transmission,
Koschmieder radiance, contrast and visibility (Eqs. 7–9) and backscatter (Eq. 12).

Units: SI inside (metres, 1/m, Hz). Config keys carry their unit (``droplet_diameter_um``,
``number_density_per_cm3``, ``extent_mm``).

Departures from the paper (see docs/physics.md):

* Table 1 gives ``Q_ext = 0.8`` at 1550 nm. Mie theory gives ``Q_ext ≈ 3.86`` for a 2.9 µm water
  droplet at 1550 nm (size parameter ≈ 5.9); we compute it with :mod:`miepython`.
* Water at 1550 nm: ``m = 1.318 + 1.2e-4 i``. The real part is Hale & Querry (1973); the imaginary
  part follows from the absorption coefficient of liquid water, α ≈ 9.7 /cm at 1.55 µm
  (Hale & Querry 1973; Kou, Labrie & Chýlek 1993), through ``k = α λ / 4π``. It changes Q_ext
  by < 0.1 %, but it makes the single-scattering albedo slightly below 1.
* Eq. (6) is written with ``Q_sc``; the attenuation of a beam is governed by extinction, so
  β = N π r² Q_ext. Absorption is included through Q_ext (the paper neglects it; at 1550 nm it
  is ~0.1 % of extinction for 3 µm droplets).

Mie is called lazily: only a fog model that needs β from droplets calls it, and only when β is
first asked for. ``fog=none`` never imports miepython.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Annotated, Any, NamedTuple

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import Range, check_ranges

__all__ = [
    "WATER_SURFACE_TENSION_N_M",
    "WATER_DENSITY_KG_M3",
    "WATER_INDEX_1550NM",
    "MieEfficiencies",
    "droplet_diameter_m",
    "mie_efficiencies",
    "extinction_per_m",
    "transmittance",
    "koschmieder_radiance",
    "koschmieder_contrast",
    "visibility_m",
    "backscatter",
    "NoFog",
    "MieFog",
    "MeasuredFog",
]

#: Surface tension of water at ~20 °C, N/m (Eq. 5).
WATER_SURFACE_TENSION_N_M = 0.072
#: Density of water, kg/m³ (Eq. 5).
WATER_DENSITY_KG_M3 = 1000.0
#: Complex refractive index ``n + i k`` of liquid water at 1550 nm (see module docstring).
WATER_INDEX_1550NM = complex(1.318, 1.2e-4)
#: Koschmieder's contrast threshold (Eq. 9).
CONTRAST_THRESHOLD = 0.05


class MieEfficiencies(NamedTuple):
    """Mie efficiencies of one sphere (dimensionless): extinction, scattering, backscattering
    (miepython's normalisation) and the asymmetry parameter g."""

    q_ext: float
    q_sca: float
    q_back: float
    g: float


#: Piezo frequencies Lang's relation is used for, Hz. Assumed: Lang (1962, J. Acoust. Soc. Am. 34, 6)
#: measured it at 10–800 kHz and ultrasonic nebulisers run up to a few MHz (the paper's 1.7 MHz);
#: [1 kHz, 1 GHz] spans that with three decades to spare and keeps the diameter between 0.4 mm
#: and 40 nm. Outside, float64 failed (measured: 1e-300 Hz a division by zero, 1e300 Hz an
#: overflow of f²).
PIEZO_RANGE_HZ = (1e3, 1e9)


#: Smallest ``droplet_diameter_um``. Assumed: 1 nm, a cluster of some 30 water molecules, is far
#: below any fog droplet (the paper's: 2.9 µm); at 1e-300 µm miepython's series divided 0 by 0
#: (measured), at 1e-3 µm the run finishes with finite numbers (measured at 8²).
DROPLET_MIN_UM = 1e-3


def droplet_diameter_m(
    piezo_frequency_hz: float,
    surface_tension_n_m: float = WATER_SURFACE_TENSION_N_M,
    density_kg_m3: float = WATER_DENSITY_KG_M3,
) -> float:
    """Median droplet diameter (m) of an ultrasonic (piezo) nebuliser, Lang's relation.

    ``d = 0.34 (8 π σ / (ρ f²))^{1/3}``  # Eq. (5)

    With water (σ = 0.072 N/m, ρ = 1000 kg/m³) at 1.7 MHz this is 2.9 µm.
    """
    lo, hi = PIEZO_RANGE_HZ
    if not np.isfinite(piezo_frequency_hz) or not lo <= piezo_frequency_hz <= hi:
        raise ConfigError("piezo_frequency_hz", piezo_frequency_hz, f"a frequency in Hz in [{lo:g}, {hi:g}]")
    return float(0.34 * (8.0 * np.pi * surface_tension_n_m / (density_kg_m3 * piezo_frequency_hz**2)) ** (1.0 / 3.0))


def mie_efficiencies(diameter_m: float, wavelength_m: float, index: complex = WATER_INDEX_1550NM) -> MieEfficiencies:
    """Mie efficiencies of a homogeneous sphere in air (miepython).

    Args:
        diameter_m: sphere diameter, m.
        wavelength_m: vacuum wavelength, m.
        index: complex refractive index ``n + i k`` with ``k >= 0`` (absorbing). miepython uses
            the ``n − i k`` sign convention; the conversion is done here.
    """
    # start-up: loads scipy, miepython, charset_normalizer (214 ms here)
    import miepython  # lazy: only fog models that need Mie pay for it

    m = complex(index.real, -abs(index.imag))
    qext, qsca, qback, g = miepython.efficiencies(m, diameter_m * 1e6, wavelength_m * 1e6)
    return MieEfficiencies(float(qext), float(qsca), float(qback), float(g))


def extinction_per_m(number_density_per_m3: float, diameter_m: float, q_ext: float) -> float:
    """Extinction coefficient β (1/m) of a monodisperse droplet cloud: ``β = N π r² Q``  # Eq. (6)"""
    r = 0.5 * diameter_m
    return float(number_density_per_m3 * np.pi * r * r * q_ext)


def transmittance(beta_per_m: float | np.ndarray, path_m: float | np.ndarray) -> np.ndarray:
    """Beer–Lambert transmittance ``τ = exp(−β z)`` (dimensionless) over ``path_m`` metres.

    ``path_m = inf`` with ``β > 0`` gives 0; ``β = 0`` gives 1 for every path (no ``0·inf``).
    """
    beta = np.asarray(beta_per_m, dtype=np.float64)
    path = np.asarray(path_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        od = np.where(beta > 0, beta * path, 0.0)
    return np.exp(-od)


def koschmieder_radiance(l_object: Any, l_fog: Any, beta_per_m: Any, z_m: Any) -> np.ndarray:
    """Apparent radiance of an object at distance z through fog (units of the inputs).

    ``L(z) = L_o e^{−βz} + L_f (1 − e^{−βz})``  # Eq. (7), Koschmieder
    """
    t = transmittance(beta_per_m, z_m)
    return np.asarray(l_object) * t + np.asarray(l_fog) * (1.0 - t)


def koschmieder_contrast(c0: Any, beta_per_m: Any, z_m: Any) -> np.ndarray:
    """Apparent contrast ``C = C_o e^{−βz}`` (dimensionless)  # Eq. (8)"""
    return np.asarray(c0) * transmittance(beta_per_m, z_m)


def visibility_m(beta_per_m: float, threshold: float = CONTRAST_THRESHOLD) -> float:
    """Koschmieder visibility (m): the distance where the contrast falls to ``threshold``.

    ``z = −ln(0.05) / β ≈ 3/β``  # Eq. (9). Infinite for β = 0.
    """
    if not 0 < threshold < 1:
        raise ConfigError("threshold", threshold, "a contrast threshold in (0, 1)")
    if beta_per_m <= 0:
        return float("inf")
    with np.errstate(over="ignore"):  # a subnormal β: the visibility is simply infinite
        return float(-np.log(threshold) / beta_per_m)


def backscatter(gain: float, radiance: Any, beta_per_m: Any, z_m: Any) -> np.ndarray:
    """Backscatter contribution ``B(z) = Ω_k D_k G_s L (1 − e^{−βz})``  # Eq. (12)

    ``gain`` lumps the paper's ``Ω_k D_k G_s`` (effective irradiance, aperture and sensor
    conversion factor; the paper gives no values) into one dimensionless factor; ``radiance``
    is ``L``, in any unit, which the result carries.
    """
    return gain * np.asarray(radiance) * (1.0 - transmittance(beta_per_m, z_m))


#: The keys both fog models share, with their declared ranges (:mod:`nirspi_pipe.ranges`).
ExtentMm = Annotated[
    float, Range(0.0, None, "a fog path length in mm", lo_open=True, finite=False, note=".inf for unbounded fog")
]
BackscatterGain = Annotated[float, Range(0.0, None, "a factor")]
FluctuationRel = Annotated[float, Range(0.0, 1.0, "a relative standard deviation")]
FluctuationTimeS = Annotated[float, Range(0.0, None, "a correlation time in s", lo_open=True)]
TrendRel = Annotated[float, Range(-0.9, 10.0, "a relative change of the density over the acquisition")]


@dataclass(frozen=True)
class NoFog:
    """``fog=none``: clear air. The simulator drops it: no Mie call, no fog array, no cost."""

    active = False
    extinction_per_m = 0.0
    backscatter_gain = 0.0
    fluctuation_rel = 0.0
    trend_rel = 0.0
    extent_m = float("inf")
    single_scattering_albedo = 1.0

    def derived(self) -> dict[str, float]:
        """Nothing to record for clear air (the simulator records β = 0 itself)."""
        return {}


@dataclass(frozen=True)
class MieFog:
    """``fog=chamber``: monodisperse water droplets, β from Mie theory (Eqs. 5–6).

    Attributes:
        piezo_frequency_hz: nebuliser frequency; gives the droplet diameter by Eq. (5). Ignored
            when ``droplet_diameter_um`` is set.
        droplet_diameter_um: droplet diameter in µm, or null to use Eq. (5).
        number_density_per_cm3: droplets per cm³ (the paper gives none; the default is
            calibrated on Table 2, see :func:`nirspi_pipe.physics.range_model.calibrate`).
        wavelength_nm: wavelength of the active light, nm.
        index_real, index_imag: refractive index ``n + i k`` of the droplets.
        extent_mm: fog path length (the chamber is 350 mm long); the fog fills
            ``min(distance, extent)`` along each ray.
        backscatter_gain: Eq. (12)'s ``Ω_k D_k G_s``, fraction of the light a white Lambertian
            target at 1 m would return; 0 turns backscatter off.
        trend_rel: relative change of the droplet density from the first to the last reading,
            linear in time (the nebuliser filling or the chamber clearing; 0 = steady).
        fluctuation_rel, fluctuation_time_s: relative standard deviation and correlation time of
            the fog density during the acquisition (Ornstein–Uhlenbeck, seeded); 0 = steady.
    """

    piezo_frequency_hz: float = 1.7e6  # its range is Eq. (5)'s: checked by droplet_diameter_m
    droplet_diameter_um: Annotated[float | None, Range(DROPLET_MIN_UM, 1e4, "a diameter in µm")] = None
    number_density_per_cm3: Annotated[float, Range(0.0, None, "a density per cm³")] = 44770.0
    wavelength_nm: Annotated[float, Range(200.0, 20000.0, "a wavelength in nm")] = 1550.0
    index_real: Annotated[float, Range(1.0, 4.0, "a real refractive index")] = WATER_INDEX_1550NM.real
    index_imag: Annotated[float, Range(0.0, 10.0, "an imaginary index k")] = WATER_INDEX_1550NM.imag
    extent_mm: ExtentMm = 350.0
    backscatter_gain: BackscatterGain = 0.01
    fluctuation_rel: FluctuationRel = 0.0
    fluctuation_time_s: FluctuationTimeS = 0.05
    trend_rel: TrendRel = 0.0

    active = True

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Import miepython (:class:`nirspi_pipe.stages.WarmsUp`); the fog's time series comes with
        the forward model (:mod:`nirspi_pipe.physics.effects`)."""
        # warm-up: loads scipy, miepython, charset_normalizer (214 ms here), before jobs fork
        import miepython  # noqa: F401

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.droplet_diameter_um is None:
            droplet_diameter_m(self.piezo_frequency_hz)  # validates the frequency

    @property
    def diameter_m(self) -> float:
        """Droplet diameter, m (given, or from Eq. 5)."""
        if self.droplet_diameter_um is not None:
            return float(self.droplet_diameter_um) * 1e-6
        return droplet_diameter_m(self.piezo_frequency_hz)

    @cached_property
    def mie(self) -> MieEfficiencies:
        """Mie efficiencies of the droplets at the wavelength (computed once, on first use)."""
        return mie_efficiencies(self.diameter_m, self.wavelength_nm * 1e-9, complex(self.index_real, self.index_imag))

    @property
    def extinction_per_m(self) -> float:
        """β in 1/m  # Eq. (6)"""
        return extinction_per_m(self.number_density_per_cm3 * 1e6, self.diameter_m, self.mie.q_ext)

    @property
    def single_scattering_albedo(self) -> float:
        """``Q_sca / Q_ext`` (dimensionless, ≤ 1)."""
        return self.mie.q_sca / self.mie.q_ext if self.mie.q_ext > 0 else 1.0

    @property
    def extent_m(self) -> float:
        """Fog path length, m."""
        return float(self.extent_mm) * 1e-3

    def derived(self) -> dict[str, float]:
        """Physical quantities this fog model used, for the record."""
        beta = self.extinction_per_m
        return {
            "droplet_diameter_um": self.diameter_m * 1e6,
            "number_density_per_cm3": float(self.number_density_per_cm3),
            "q_ext": self.mie.q_ext,
            "q_sca": self.mie.q_sca,
            "single_scattering_albedo": self.single_scattering_albedo,
            "beta_per_m": beta,
            **({"visibility_m": visibility_m(beta)} if np.isfinite(visibility_m(beta)) else {}),
        }


@dataclass(frozen=True)
class MeasuredFog:
    """``fog=measured``: β given as measured (e.g. by the paper's moving-mirror method); no Mie.

    Attributes:
        beta_per_m: extinction coefficient, 1/m.
        extent_mm, backscatter_gain, fluctuation_rel, fluctuation_time_s: as in :class:`MieFog`.
        single_scattering_albedo: ``Q_sca/Q_ext`` used for fog airlight under background light.
    """

    beta_per_m: Annotated[float, Range(0.0, None, "an extinction coefficient in 1/m")] = 1.0
    extent_mm: ExtentMm = 350.0
    backscatter_gain: BackscatterGain = 0.01
    fluctuation_rel: FluctuationRel = 0.0
    fluctuation_time_s: FluctuationTimeS = 0.05
    trend_rel: TrendRel = 0.0
    single_scattering_albedo: Annotated[float, Range(0.0, 1.0, "a value")] = 1.0

    active = True

    def __post_init__(self) -> None:
        check_ranges(self)

    @property
    def extinction_per_m(self) -> float:
        """β in 1/m, as given."""
        return float(self.beta_per_m)

    @property
    def extent_m(self) -> float:
        """Fog path length, m."""
        return float(self.extent_mm) * 1e-3

    def derived(self) -> dict[str, float]:
        """Physical quantities this fog model used, for the record."""
        beta = self.extinction_per_m
        vis = visibility_m(beta)
        return {"beta_per_m": beta, **({"visibility_m": vis} if np.isfinite(vis) else {})}  # subnormal β: inf
