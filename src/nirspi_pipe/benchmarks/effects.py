"""``nirspi-bench effects``: simulation time grows with the effects enabled, not the available.

Times ``Simulator.acquire`` on the same rendered sphere for a series of configurations and
reports each against the bare simulator (no effects at all), timed back to back with it in every
round (the median ratio over the rounds), so that the load of a shared machine cancels:

* ``available, off``: every effect configured but inactive (``fog=none``, 0 kLux, ideal
  detector) — must cost the same as the bare simulator (ratio ≈ 1);
* then the effects switched on one at a time and all together.
"""

from __future__ import annotations

import argparse

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.physics.detector import IdealDetector, Photodiode
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.physics.fog import MieFog, NoFog
from nirspi_pipe.physics.light import Background
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera


def configurations() -> dict[str, Simulator]:
    """The benchmarked simulators, reference first."""
    fog = MieFog()
    _ = fog.extinction_per_m  # Mie once, outside the timing (it is cached per fog model)
    fog_tv = MieFog(fluctuation_rel=0.1)
    _ = fog_tv.extinction_per_m
    return {
        "bare (reference)": Simulator(),
        "available, off": Simulator(
            forward_model(fog=NoFog(), illumination=Background(klux=0.0), detector=IdealDetector())
        ),
        "+ detector (budget, noise, ADC)": Simulator(forward_model(detector=Photodiode())),
        "+ fog": Simulator(forward_model(fog=fog)),
        "+ background 15 kLux": Simulator(forward_model(illumination=Background(klux=15.0))),
        "+ background drift/flicker": Simulator(
            forward_model(illumination=Background(klux=15.0, drift_rel_per_s=0.1, flicker_rel=0.05))
        ),
        "+ fog fluctuation": Simulator(forward_model(fog=fog_tv)),
        "all": Simulator(
            forward_model(
                fog=fog_tv,
                illumination=Background(klux=15.0, drift_rel_per_s=0.1, flicker_rel=0.05),
                detector=Photodiode(),
            )
        ),
    }


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench effects", description=__doc__)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=9)
    ns = parser.parse_args(argv)
    n = ns.size
    scene = Sphere().render(Camera(n))
    idx = np.arange(n * n)
    print(f"{n}x{n} sphere, {n * n} pattern pairs; ratio = median over {ns.repeat} rounds of (config / bare),")
    print("each round timing the bare simulator and the configuration back to back (robust to machine load)")
    print(f"{'configuration':<34} {'ms':>9} {'ratio':>7}  effects")
    sims = configurations()
    bare = sims["bare (reference)"]

    def once(sim: Simulator) -> float:
        return median_time_s(lambda: sim.acquire(scene, idx, n, np.random.default_rng(0)), 1, 0.01)

    for name, sim in sims.items():
        pairs = [(once(bare), once(sim)) for _ in range(ns.repeat)]
        t = float(np.median([b for _, b in pairs]))
        ratio = float(np.median([b / a for a, b in pairs]))
        print(f"{name:<34} {t * 1e3:>9.3f} {ratio:>7.2f}  {','.join(sim.effect_names) or '-'}")
    return 0
