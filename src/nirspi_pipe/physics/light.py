"""Background light: illuminance in kLux → irradiance and photon flux in the detector's band.

The conversion (docs/physics.md, "Background light"):

1. The spectrum is a choice (``spectrum``):

   * ``sun`` (default): the ASTM G173-03 AM1.5 global-tilt reference spectrum, tabulated in
     ``physics/data/astm_g173_global.csv`` (360–1800 nm: the photopic range for the illuminance and
     the InGaAs range for the band; copied from the table pvlib ships). Its 1500–1600 nm band carries 25.5 W/m²
     of the standard's 1000 W/m².
   * ``halogen``: a halogen lamp, a blackbody at ``spectrum_temperature_k`` (3000 K assumed: the
     colour temperature of tungsten-halogen lamps is 2800–3200 K).
   * ``blackbody``: a blackbody at ``spectrum_temperature_k`` (5778 K = the Sun's effective
     temperature, the model before the tabulated spectrum; no atmospheric absorption bands).

   Each source has its own time behaviour (:meth:`Background.flicker_amplitude`): the sun has no
   mains flicker; a lamp on 50 Hz mains flickers at 100 Hz with the amplitude its filament's
   thermal inertia leaves (:func:`filament_flicker_rel`).
2. Illuminance is ``E_v = 683 lm/W · ∫ V(λ) E_e(λ) dλ`` with the CIE photopic luminosity function
   V(λ) (Gaussian approximation ``1.019 exp(−285.4 (λ/µm − 0.559)²)``). For 5778 K this gives a
   luminous efficacy of ≈ 93 lm/W of total irradiance, so 100 kLux ≈ 1.08 kW/m² (direct
   sunlight, as expected).
3. The irradiance the detector can see is the part of the spectrum inside ``band_nm``. The
   default is a 100 nm band-pass around the 1550 nm LED line (1500–1600 nm): the paper names no
   filter, but without one the InGaAs photodiode (800–1700 nm) would see ~20× more sunlight
   and saturate below 15 kLux. ``band_nm: [800, 1700]`` models the bare photodiode.
4. The photon flux in the band is ``∫ E_e(λ) λ/(hc) dλ`` over the same spectrum.

How that irradiance becomes photoelectrons at the photodiode (a Lambertian scene seen through
the lens, Eqs. 10–11) is in :mod:`nirspi_pipe.physics.budget`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Annotated

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import OneOf, Range, check_ranges

__all__ = [
    "SPECTRA",
    "astm_g173_global",
    "filament_flicker_rel",
    "H_PLANCK",
    "C_LIGHT",
    "K_BOLTZMANN",
    "planck_spectral_irradiance",
    "photopic_luminosity",
    "luminous_efficacy_lm_per_w",
    "band_fraction",
    "klux_to_irradiance_w_m2",
    "klux_to_photon_irradiance",
    "Background",
]

H_PLANCK = 6.62607015e-34  # J s
C_LIGHT = 299792458.0  # m/s
K_BOLTZMANN = 1.380649e-23  # J/K
_KM = 683.0  # lm/W, maximum luminous efficacy
#: The background spectra (``illumination.spectrum``).
SPECTRA = ("sun", "halogen", "blackbody")


@lru_cache(maxsize=1)
def astm_g173_global() -> tuple[np.ndarray, np.ndarray]:
    """ASTM G173-03 AM1.5 global-tilt spectral irradiance: wavelengths (m) and W m⁻² m⁻¹, over
    the rows kept in ``physics/data/astm_g173_global.csv`` (360–1800 nm)."""
    path = resources.files("nirspi_pipe.physics").joinpath("data").joinpath("astm_g173_global.csv")
    with path.open() as fh:
        data = np.loadtxt(fh, delimiter=",", comments="#", skiprows=5)
    return data[:, 0] * 1e-9, data[:, 1] * 1e9


def filament_flicker_rel(
    time_constant_s: float, mains_hz: float = 50.0, temperature_k: float = 3000.0, wavelength_nm: float = 1550.0
) -> float:
    """Relative amplitude of a filament lamp's in-band radiance ripple at ``2 mains_hz``.

    The electrical power ``P₀ (1 − cos 2ωt)`` heats a filament that radiates ``∝ T⁴`` and has a
    thermal time constant τ: a first-order low-pass leaves a temperature ripple
    ``ΔT/T = ¼ / √(1 + (2ωτ)²)``, and the spectral radiance at λ changes as
    ``d ln B/d ln T = x/(1 − e^{−x})`` with ``x = hc/(λkT)`` (Planck). Dimensionless."""
    x = H_PLANCK * C_LIGHT / (wavelength_nm * 1e-9 * K_BOLTZMANN * temperature_k)
    sensitivity = x / -np.expm1(-x)
    w = 2.0 * np.pi * 2.0 * mains_hz
    return float(0.25 * sensitivity / np.sqrt(1.0 + (w * time_constant_s) ** 2))


def planck_spectral_irradiance(wavelength_m: np.ndarray, temperature_k: float) -> np.ndarray:
    """Blackbody spectral shape ``2hc²/λ⁵ / (exp(hc/λkT) − 1)`` (W m⁻³ sr⁻¹; only its shape is
    used, the scale is set by the illuminance)."""
    lam = np.asarray(wavelength_m, dtype=np.float64)
    x = H_PLANCK * C_LIGHT / (lam * K_BOLTZMANN * temperature_k)
    return 2 * H_PLANCK * C_LIGHT**2 / lam**5 / np.expm1(np.minimum(x, 700.0))


def photopic_luminosity(wavelength_m: np.ndarray) -> np.ndarray:
    """CIE photopic luminosity function V(λ), Gaussian approximation (peak 1 at 555–559 nm)."""
    um = np.asarray(wavelength_m, dtype=np.float64) * 1e6
    return 1.019 * np.exp(-285.4 * (um - 0.559) ** 2)


def _grid(lo_m: float, hi_m: float, n: int = 4001) -> np.ndarray:
    return np.linspace(lo_m, hi_m, n)


@lru_cache(maxsize=64)
def luminous_efficacy_lm_per_w(temperature_k: float = 5778.0) -> float:
    """Luminous efficacy (lm per W of total irradiance) of a blackbody spectrum."""
    lam = _grid(100e-9, 100e-6, 200001)
    spec = planck_spectral_irradiance(lam, temperature_k)
    total = np.trapezoid(spec, lam)
    lum = _KM * np.trapezoid(spec * photopic_luminosity(lam), lam)
    return float(lum / total)


@lru_cache(maxsize=64)
def band_fraction(band_nm: tuple[float, float], temperature_k: float = 5778.0) -> tuple[float, float]:
    """Fraction of a blackbody's total irradiance inside ``band_nm`` (dimensionless), and the
    photon flux per watt of *total* irradiance inside the band (photons s⁻¹ W⁻¹)."""
    lam_all = _grid(100e-9, 100e-6, 200001)
    total = np.trapezoid(planck_spectral_irradiance(lam_all, temperature_k), lam_all)
    lam = _grid(band_nm[0] * 1e-9, band_nm[1] * 1e-9)
    spec = planck_spectral_irradiance(lam, temperature_k)
    frac = np.trapezoid(spec, lam) / total
    photons_per_w = np.trapezoid(spec * lam / (H_PLANCK * C_LIGHT), lam) / total
    return float(frac), float(photons_per_w)


@lru_cache(maxsize=64)
def _sun_per_lux(band_nm: tuple[float, float]) -> tuple[float, float]:
    """ASTM G173 global: in-band W/m² and photons s⁻¹ m⁻² per lux of its illuminance."""
    lam, e = astm_g173_global()
    vis = lam <= 830e-9
    lux = _KM * np.trapezoid(e[vis] * photopic_luminosity(lam[vis]), lam[vis])
    lo, hi = band_nm[0] * 1e-9, band_nm[1] * 1e-9
    if lo < 360e-9 or hi > 1800e-9:
        raise ConfigError("band_nm", list(band_nm), "a band inside 360-1800 nm for spectrum=sun (the tabulated rows)")
    grid = np.linspace(lo, hi, 2001)
    e_band = np.interp(grid, lam, e)
    watts = np.trapezoid(e_band, grid)
    photons = np.trapezoid(e_band * grid / (H_PLANCK * C_LIGHT), grid)
    return float(watts / lux), float(photons / lux)


def klux_to_irradiance_w_m2(
    klux: float,
    band_nm: tuple[float, float] = (1500.0, 1600.0),
    temperature_k: float = 5778.0,
    spectrum: str = "blackbody",
) -> float:
    """Irradiance (W/m²) inside ``band_nm`` of an illuminance of ``klux`` kilolux, with the
    ``spectrum`` of :data:`SPECTRA` (``temperature_k`` for a blackbody or halogen lamp)."""
    if spectrum == "sun":
        return klux * 1e3 * _sun_per_lux(tuple(band_nm))[0]
    total = klux * 1e3 / luminous_efficacy_lm_per_w(temperature_k)
    return total * band_fraction(tuple(band_nm), temperature_k)[0]


def klux_to_photon_irradiance(
    klux: float,
    band_nm: tuple[float, float] = (1500.0, 1600.0),
    temperature_k: float = 5778.0,
    spectrum: str = "blackbody",
) -> float:
    """Photon irradiance (photons s⁻¹ m⁻²) inside ``band_nm`` of ``klux`` kilolux (see
    :func:`klux_to_irradiance_w_m2`)."""
    if spectrum == "sun":
        return klux * 1e3 * _sun_per_lux(tuple(band_nm))[1]
    total = klux * 1e3 / luminous_efficacy_lm_per_w(temperature_k)
    return total * band_fraction(tuple(band_nm), temperature_k)[1]


#: Highest ``mains_hz`` and ``flicker_hz``, Hz. Assumed: mains are 50/60 Hz (400 Hz aboard
#: aircraft) and lamp flicker twice that; 1 GHz is beyond any light source's modulation the
#: 150 µs integration could follow. Above it ``2π f t`` overflowed float64 (measured:
#: flicker_hz = 1e300 at one pattern per 1e300 s gave sin(inf) = NaN).
MAX_HZ = 1e9


@dataclass(frozen=True)
class Background:
    """Background (ambient) light on the scene: ``illumination=none|klux``.

    Attributes:
        klux: illuminance on the scene, kLux, in [0, 100] (0 = dark).
        band_nm: detector band ``[lo, hi]`` in nm (see the module docstring).
        spectrum: ``sun`` (ASTM G173 AM1.5 global), ``halogen`` or ``blackbody`` (module docstring).
        spectrum_temperature_k: temperature of the halogen or blackbody spectrum, K (the sun's
            tabulated spectrum ignores it).
        filament_time_s: thermal time constant of a halogen lamp's filament, s (sets its flicker,
            :func:`filament_flicker_rel`).
        mains_hz: mains frequency of a lamp, Hz (50 Hz in Europe; flicker at twice it).
        surround_reflectance: Lambertian reflectance of what the camera sees around the object
            (the chamber walls), in [0, 1].
        drift_rel_per_s: linear drift of the level, relative per second (time-varying).
        flicker_rel, flicker_hz: sinusoidal flicker amplitude (relative) and frequency (Hz); with
            ``flicker_rel: null`` the source's own (:meth:`flicker_amplitude`): 0 for the sun and
            a blackbody, the filament's for a halogen lamp at ``2 mains_hz``.
        wander_rel, wander_time_s: random slow fluctuation (Ornstein–Uhlenbeck, seeded):
            relative standard deviation and correlation time.
    """

    klux: Annotated[float, Range(0.0, 100.0, "an illuminance in kLux")] = 0.0
    band_nm: tuple[float, float] = (1500.0, 1600.0)
    spectrum: Annotated[str, OneOf(SPECTRA)] = "blackbody"
    spectrum_temperature_k: Annotated[float, Range(1000.0, 20000.0, "a temperature in K")] = 5778.0
    filament_time_s: Annotated[float, Range(0.0, None, "a thermal time constant in s", lo_open=True)] = 0.05
    # a halogen lamp flickers at twice its mains frequency: at most MAX_HZ
    mains_hz: Annotated[float, Range(0.0, MAX_HZ / 2, "a mains frequency in Hz", lo_open=True)] = 50.0
    surround_reflectance: Annotated[float, Range(0.0, 1.0, "a reflectance")] = 0.2
    drift_rel_per_s: Annotated[float, Range(-10.0, 10.0, "a relative drift per s")] = 0.0
    flicker_rel: Annotated[float | None, Range(0.0, 10.0, "a relative amount")] = 0.0
    flicker_hz: Annotated[float, Range(0.0, MAX_HZ, "a frequency in Hz")] = 100.0
    wander_rel: Annotated[float, Range(0.0, 10.0, "a relative amount")] = 0.0
    wander_time_s: Annotated[float, Range(0.0, None, "a correlation time in s", lo_open=True)] = 0.1

    def __post_init__(self) -> None:
        check_ranges(self)
        band = tuple(float(b) for b in self.band_nm)
        if len(band) != 2 or not 200.0 <= band[0] < band[1] <= 20000.0:
            raise ConfigError("band_nm", self.band_nm, "[lo, hi] in nm with 200 <= lo < hi <= 20000")
        object.__setattr__(self, "band_nm", band)
        if self.spectrum == "sun" and not 360.0 <= band[0] < band[1] <= 1800.0:
            raise ConfigError("band_nm", list(band), "a band inside 360-1800 nm for spectrum=sun (the tabulated rows)")
        if self.flicker_rel is None:  # the source's own, within range by construction
            object.__setattr__(self, "flicker_rel", self.flicker_amplitude())
            if self.spectrum == "halogen":
                object.__setattr__(self, "flicker_hz", 2.0 * self.mains_hz)

    def flicker_amplitude(self) -> float:
        """The source's own flicker (relative): none for the sun (no mains) or a generic blackbody;
        for a halogen lamp, the ripple its filament's thermal inertia leaves at ``2 mains_hz``."""
        if self.spectrum != "halogen":
            return 0.0
        centre = 0.5 * (self.band_nm[0] + self.band_nm[1])
        return filament_flicker_rel(self.filament_time_s, self.mains_hz, self.spectrum_temperature_k, centre)

    @property
    def active(self) -> bool:
        """False at 0 kLux: the simulator then does not build this effect."""
        return self.klux > 0.0

    @property
    def time_varying(self) -> bool:
        """Whether the level changes during the acquisition."""
        return bool(self.drift_rel_per_s or self.flicker_rel or self.wander_rel)

    @property
    def irradiance_w_m2(self) -> float:
        """In-band irradiance on the scene, W/m²."""
        return klux_to_irradiance_w_m2(self.klux, self.band_nm, self.spectrum_temperature_k, self.spectrum)

    @property
    def photon_irradiance(self) -> float:
        """In-band photon irradiance on the scene, photons s⁻¹ m⁻²."""
        return klux_to_photon_irradiance(self.klux, self.band_nm, self.spectrum_temperature_k, self.spectrum)
