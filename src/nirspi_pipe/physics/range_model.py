"""Maximum measurement distance of the NIR-SPI camera (Algorithm A1) and the calibration of its
free constants on Table 2.

The model (docs/physics.md, "Range model"): a Lambertian target of reflectance R fills the view
on the axis at distance z. With all LEDs on, the photodiode collects

``S(z) = R · N_white(z) · e^{−2βz}``  (e⁻; N_white ∝ 1/z², Eq. 10; round trip through fog)

and one LED patch of the 8 × 8 array contributes ``S/led_count``: the signal a resolvable pixel
carries. A reading (one half pattern) has the noise of
:meth:`~nirspi_pipe.physics.detector.Photodiode.noise_e` (read-noise floor, dark, background,
backscatter and signal shot noise) on its mean charge ``S/2 + B(z)/2 + background``. The
maximum distance is where the patch signal meets the noise: ``S/led_count = k · σ`` with
``k = snr_threshold = 1`` (Alg. A1, line 13: ``|E(N) − σ_noisefloor| < δ_th``).

Without fog and background, the signal-dependent part of σ is the same at the threshold for
every R, so the floor is fixed and ``z_max ∝ √R`` (Table 2: 22.4 : 35 : 44). With fog, ``z_max``
solves ``z e^{βz} = z_max(β = 0)``, so one β reproduces the fog row.

Instead of the paper's fixed steps of Z_max/10, :func:`max_distance_m` scans a fine logarithmic
grid for the first crossing and refines it by bisection (to 1 nm; scipy.optimize is not
imported because its import alone costs more than a simulation).
"""

from __future__ import annotations

import csv
from dataclasses import replace
from functools import lru_cache
from importlib import resources
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.detector import Photodiode
from nirspi_pipe.physics.fog import MieFog, backscatter, koschmieder_radiance

__all__ = [
    "bisect",
    "signal_electrons",
    "reading_noise_electrons",
    "snr",
    "max_distance_m",
    "paper_table2",
    "CALIBRATION_CELLS",
    "calibrate",
]

#: The two Table 2 cells the two free constants are calibrated on: (row, R).
#: The no-fog cell fixes the read-noise floor, the fog cell fixes the droplet number density.
CALIBRATION_CELLS = (("theory_no_fog", 0.5), ("theory_fog", 0.2))


def bisect(fn: Any, lo: float, hi: float, xtol: float = 1e-9) -> float:
    """Root of ``fn`` in ``[lo, hi]`` by bisection (``fn(lo)`` and ``fn(hi)`` of opposite signs,
    or a zero at an end)."""
    f_lo = fn(lo)
    if f_lo == 0:
        return float(lo)
    for _ in range(200):
        if hi - lo <= xtol * max(1.0, abs(lo)):
            break
        mid = 0.5 * (lo + hi)
        f_mid = fn(mid)
        if f_mid == 0:
            return float(mid)
        if (f_mid > 0) == (f_lo > 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return float(0.5 * (lo + hi))


def signal_electrons(
    z_m: Any, reflectance: float, budget: PhotonBudget, beta_per_m: float = 0.0, fog_extent_m: float = float("inf")
) -> np.ndarray:
    """Photoelectrons per integration, all LEDs on, from an on-axis Lambertian target of
    ``reflectance`` filling the view at ``z_m`` metres through fog of extinction ``beta_per_m``
    that fills ``min(z, fog_extent_m)`` of the path (round trip; the chamber is 35 cm deep):
    ``R N_white(z) e^{−2β min(z, ℓ)}``  # Eqs. (6), (10)."""
    z = np.asarray(z_m, dtype=np.float64)
    return reflectance * budget.white_electrons(z) * np.exp(-2.0 * beta_per_m * np.minimum(z, fog_extent_m))


def reading_noise_electrons(
    z_m: Any,
    reflectance: float,
    detector: Photodiode,
    beta_per_m: float = 0.0,
    backscatter_gain: float = 0.0,
    fog_extent_m: float = float("inf"),
    photon_irradiance: float = 0.0,
    albedo: float = 1.0,
) -> np.ndarray:
    """Noise (e⁻ rms) of one half-pattern reading of the target at ``z_m`` metres.

    Mean charge: half the signal, half the backscatter veil ``B(z)`` (Eq. 12, relative to a white
    target at 1 m) and the ambient light (Koschmieder radiance of the target, Eq. 7, with the
    fog's airlight ``albedo``)."""
    z = np.asarray(z_m, dtype=np.float64)
    budget = detector.budget
    s = signal_electrons(z, reflectance, budget, beta_per_m, fog_extent_m)
    fog_path = np.minimum(z, fog_extent_m)
    veil = backscatter(backscatter_gain, budget.white_electrons(1.0), beta_per_m, fog_path)
    ambient = budget.ambient_electrons(
        photon_irradiance, koschmieder_radiance(reflectance, albedo, beta_per_m, fog_path)
    )
    return detector.noise_e(0.5 * (s + veil) + ambient)


def snr(z_m: Any, reflectance: float, detector: Photodiode, **conditions: Any) -> np.ndarray:
    """Signal of one LED patch over the reading noise (dimensionless) at ``z_m`` metres."""
    beta = conditions.get("beta_per_m", 0.0)
    extent = conditions.get("fog_extent_m", float("inf"))
    patch = signal_electrons(z_m, reflectance, detector.budget, beta, extent) / detector.budget.led_count
    noise = reading_noise_electrons(z_m, reflectance, detector, **conditions)
    return patch / np.maximum(noise, 1e-300)


def max_distance_m(
    reflectance: float,
    detector: Photodiode,
    snr_threshold: float = 1.0,
    z_min_m: float = 1e-3,
    z_max_m: float = 10.0,
    **conditions: Any,
) -> float:
    """Algorithm A1: the largest distance (m) at which the patch signal still meets the noise.

    Args:
        reflectance: target reflectance R in [0, 1].
        detector: the photodiode (its photon budget and noise).
        snr_threshold: the SNR at the limit (1: the signal meets the noise floor).
        z_min_m, z_max_m: the search range, m ("field-far measurement" Z_max of Alg. A1).
        **conditions: ``beta_per_m``, ``backscatter_gain``, ``fog_extent_m``,
            ``photon_irradiance``, ``albedo`` (see :func:`reading_noise_electrons`).

    Returns ``z_min_m`` when even the nearest distance is below the threshold (e.g. R = 0) and
    ``z_max_m`` when the farthest is still above it. Always finite.
    """
    if not 0.0 <= reflectance <= 1.0:
        raise ConfigError("reflectance", reflectance, "a reflectance in [0, 1]")
    if not 0 < z_min_m < z_max_m or not np.isfinite(z_max_m):
        raise ConfigError("z_max_m", z_max_m, f"a finite distance in m > z_min_m = {z_min_m}")
    if not snr_threshold > 0:
        raise ConfigError("snr_threshold", snr_threshold, "an SNR > 0")
    beta = float(conditions.get("beta_per_m", 0.0))
    if not np.isfinite(beta) or beta < 0:
        raise ConfigError("beta_per_m", beta, "an extinction coefficient >= 0 in 1/m")
    key = (float(reflectance), detector, float(snr_threshold), float(z_min_m), float(z_max_m))
    try:
        return _remembered_max_distance(*key, tuple(sorted(conditions.items())))
    except TypeError:  # an unhashable detector or condition (an array): computed each time
        return _max_distance(reflectance, detector, snr_threshold, z_min_m, z_max_m, conditions)


@lru_cache(maxsize=256)
def _remembered_max_distance(
    reflectance: float,
    detector: Photodiode,
    snr_threshold: float,
    z_min_m: float,
    z_max_m: float,
    conditions: tuple[tuple[str, Any], ...],
) -> float:
    """:func:`_max_distance`, remembered: a pure function of its (hashable, immutable) arguments,
    which the jobs of a sweep repeat (a figure9 job's range is the same for every scan and seed of
    its scene, light and fog; 2-3 ms of its source stage each time)."""
    return _max_distance(reflectance, detector, snr_threshold, z_min_m, z_max_m, dict(conditions))


def _max_distance(
    reflectance: float,
    detector: Photodiode,
    snr_threshold: float,
    z_min_m: float,
    z_max_m: float,
    conditions: dict[str, Any],
) -> float:
    """The search of :func:`max_distance_m` on checked arguments."""

    def excess(z: float) -> float:
        return float(np.log(max(float(snr(z, reflectance, detector, **conditions)), 1e-300)) - np.log(snr_threshold))

    grid = np.geomspace(z_min_m, z_max_m, 512)
    values = np.log(np.maximum(snr(grid, reflectance, detector, **conditions), 1e-300)) - np.log(snr_threshold)
    if values[0] < 0:
        return float(z_min_m)
    below = np.nonzero(values < 0)[0]
    if below.size == 0:
        return float(z_max_m)
    i = int(below[0])
    return bisect(excess, float(grid[i - 1]), float(grid[i]), xtol=1e-9)


def paper_table2() -> dict[str, dict[float, float]]:
    """The paper's Table 2 in metres: ``{row: {R: z_max}}`` from experiments/reference/table2.csv."""
    path = resources.files("nirspi_pipe.experiments").joinpath("reference").joinpath("table2.csv")
    out: dict[str, dict[float, float]] = {}
    with path.open() as fh:
        for row in csv.DictReader(fh):
            out[row["row"]] = {float(k.split("=")[1]): float(v) * 1e-2 for k, v in row.items() if k.startswith("R=")}
    return out


def calibrate(detector: Photodiode | None = None, fog: Any = None) -> dict[str, float]:
    """Calibrate the two free constants on :data:`CALIBRATION_CELLS` of the paper's Table 2.

    1. The read-noise floor ``read_noise_e``: with everything else at its default, the no-fog
       distance of R = 0.5 must be 35 cm. Solved in closed form from the noise at that distance.
    2. The droplet number density: the fog distance of R = 0.2 must be 18 cm. β is found by
       bisection, then ``N = β / (π r² Q_ext)`` (Eq. 6) with Q_ext from Mie.

    Every other Table 2 cell is then a prediction. Returns ``read_noise_e``, ``beta_per_m`` and
    ``number_density_per_cm3``; conf/detector/ingaas.yaml and conf/fog/chamber.yaml hold these
    values (a test checks they agree).
    """
    detector = detector if detector is not None else Photodiode()
    fog = fog if fog is not None else MieFog()
    paper = paper_table2()
    (row0, r0), (row1, r1) = CALIBRATION_CELLS
    z0 = paper[row0][r0]
    budget = detector.budget
    s = float(signal_electrons(z0, r0, budget))
    patch = s / budget.led_count
    base = replace(detector, read_noise_e=0.0)
    var_rest = float(base.noise_e(0.5 * s)) ** 2
    if patch**2 <= var_rest:
        raise ValueError("the calibration cell is shot-noise limited; no read-noise floor fits it")
    read = float(np.sqrt(patch**2 - var_rest))
    det = replace(detector, read_noise_e=read)

    z1 = paper[row1][r1]
    cond = {"backscatter_gain": fog.backscatter_gain, "fog_extent_m": fog.extent_m}

    def miss(beta: float) -> float:
        return max_distance_m(r1, det, beta_per_m=beta, **cond) - z1

    beta = bisect(miss, 0.0, 100.0, xtol=1e-12)
    r = 0.5 * fog.diameter_m
    n_per_m3 = beta / (np.pi * r * r * fog.mie.q_ext)
    return {"read_noise_e": read, "beta_per_m": beta, "number_density_per_cm3": n_per_m3 * 1e-6}


if __name__ == "__main__":  # pragma: no cover - prints the calibration for the config files
    print(calibrate())
