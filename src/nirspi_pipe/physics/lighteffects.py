"""The forward model's built-in effects of light (paper Eqs. 7, 10–11): the active light and its
photon budget (:class:`Illumination`, image stage) and the ambient light (:class:`BackgroundLight`,
and its drift, flicker and wander during the acquisition, :class:`BackgroundDrift`; readings stage).
:func:`nirspi_pipe.physics.effects.forward_model` chains them with the other effects. Moved out of
:mod:`nirspi_pipe.physics.effects` (issue 42 item 5).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar, Literal

import numpy as np

from nirspi_pipe.physics.budget import PhotonBudget
from nirspi_pipe.physics.fog import koschmieder_radiance
from nirspi_pipe.physics.light import Background
from nirspi_pipe.physics.stagetypes import AmbientCharge, Exposure, ImageState, Readings
from nirspi_pipe.physics.timevarying import background_factor

__all__ = ["BackgroundDrift", "BackgroundLight", "Illumination"]


@dataclass(frozen=True)
class Illumination:
    """The active light and photon budget: each pixel gets ``ρ N_white(r)/n²`` e⁻ with the
    1/r² fall-off of its own range ``r`` (Eqs. 10–11). Without it (ideal detector) every pixel
    gets ``ρ N_white(z_nom)/n²``: no fall-off across the object. In the reference."""

    budget: PhotonBudget = field(default_factory=PhotonBudget)

    name: ClassVar[str] = "budget"
    domain: ClassVar[Literal["image"]] = "image"
    in_reference: ClassVar[bool] = True

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        r = exposure.range_m
        finite = np.isfinite(r)
        n2 = exposure.n * exposure.n
        img = (
            exposure.scene.radiance * np.where(finite, self.budget.white_electrons(np.where(finite, r, 1.0)), 0.0) / n2
        )
        return replace(image, image_e=img)


@dataclass(frozen=True)
class BackgroundLight:
    """Ambient light (Eqs. 7, 10–11): the same charge on every reading, from the scene's mean
    reflectance (object and surround, seen through the fog's airlight by Koschmieder when the
    fog effect is in the chain). ``background`` is a
    :class:`~nirspi_pipe.physics.light.Background`. Not in the reference: a steady background
    cancels in the split difference."""

    background: Background

    name: ClassVar[str] = "background"
    domain: ClassVar[Literal["readings"]] = "readings"
    in_reference: ClassVar[bool] = False

    def apply(self, readings: Readings, exposure: Exposure) -> Readings:
        bg, scene, med = self.background, exposure.scene, readings.medium
        cov = scene.coverage
        if med is not None:
            path = np.where(np.isfinite(med.path_m), med.path_m, 0.0)
            obj = koschmieder_radiance(scene.reflectance, med.albedo, med.beta_per_m, path)
            wall = koschmieder_radiance(bg.surround_reflectance, med.albedo, med.beta_per_m, med.extent_m)
        else:
            obj, wall = scene.reflectance, np.asarray(bg.surround_reflectance)
        refl = float(np.mean(cov * obj + (1.0 - cov) * wall))
        bg_e = float(exposure.budget.ambient_electrons(bg.photon_irradiance, refl))
        return replace(
            readings,
            ambient=AmbientCharge.steady(bg_e),
            conditions={**readings.conditions, "photon_irradiance": float(bg.photon_irradiance)},
        ).with_derived(klux=float(bg.klux), background_irradiance_w_m2=float(bg.irradiance_w_m2))


@dataclass(frozen=True)
class BackgroundDrift:
    """The background level changes during the acquisition: ``1 + drift·t + flicker·sin(2πft + φ)
    + OU`` per reading (:func:`~nirspi_pipe.physics.timevarying.background_factor`), so it no
    longer cancels exactly in ``y_pos − y_neg``. Not in the reference."""

    drift_rel_per_s: float = 0.0
    flicker_rel: float = 0.0
    flicker_hz: float = 100.0
    wander_rel: float = 0.0
    wander_time_s: float = 0.1

    name: ClassVar[str] = "background_drift"
    domain: ClassVar[Literal["readings"]] = "readings"
    in_reference: ClassVar[bool] = False
    streams: ClassVar[tuple[int, ...]] = (1,)

    def apply(self, readings: Readings, exposure: Exposure) -> Readings:
        amb = readings.ambient
        if amb is None:
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
        bg_e = amb.level_e
        drifting = replace(amb, pos=bg_e * fac[:m], neg=bg_e * fac[m : 2 * m], dark=bg_e * fac[2 * m :])
        return replace(readings, ambient=drifting).with_derived(background_factor_std=float(np.std(fac)))
