"""The physical model of the NIR-SPI camera in the fog chamber (docs/physics.md).

* :mod:`.fog` — droplet size (Eq. 5), Mie (miepython, lazily), extinction (Eq. 6), Beer–Lambert,
  Koschmieder (Eqs. 7–9), backscatter (Eq. 12); fog models ``NoFog``, ``MieFog``, ``MeasuredFog``.
* :mod:`.light` — kLux → in-band irradiance and photon flux; the ``Background`` effect.
* :mod:`.budget` — the photon budget at the photodiode (Eqs. 10–11), ``PhotonBudget``.
* :mod:`.detector` — ``IdealDetector`` and the InGaAs ``Photodiode`` (shot, dark, read noise,
  saturation, ADC).
* :mod:`.timevarying` — background drift/flicker/wander and fog fluctuation (seeded).
* :mod:`.range_model` — Algorithm A1 and the calibration of its free constants on Table 2.
* :mod:`.effects` — the forward model as a chain of small effect objects (illumination, fog
  attenuation, fog fluctuation, backscatter, background light, drift, detector, Gaussian noise),
  the public :class:`~.effects.Effect` interface, and :func:`~.effects.forward_model`.

The simulator (:mod:`nirspi_pipe.sources.simulator`) applies the chain the runner built from the config.
"""
