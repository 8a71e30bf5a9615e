"""``nirspi-bench fista``: FISTA-TV iterations per second, against its own floor; ``--auto``: the
whole default solve (weight chosen from the data) against the fast inverse and a fixed-weight solve.

One FISTA iteration is a forward and an adjoint fast transform (the gradient) plus a TV
proximal step. The peers, timed in the same run on the same image: the transform pair alone
(the floor of any iterative solver here) and the TV prox alone (scikit-image Chambolle).

``--auto``: per size and case (camera image, zig-zag at ``--ratio``; ``free``: ideal detector;
``device``: InGaAs photodiode, 15 kLux, the paper's noise), the median time of ``fwht`` (the
zero-filled inverse), of ``fista_tv`` with ``lam: auto`` and of ``fista_tv`` at the weight ``auto``
chose (one solve): ``auto / fixed − 1`` is what choosing the weight costs, in solves.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from skimage.restoration import denoise_tv_chambolle

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.physics.detector import IdealDetector, Photodiode
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.physics.light import Background
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.common import hadamard_operator
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench fista", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128])
    parser.add_argument("--ratio", type=float, default=0.25)
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--auto", action="store_true", help="time the default solve (lam: auto) instead")
    parser.add_argument("--repeat", type=int, default=7)
    ns = parser.parse_args(argv)
    if ns.auto:
        return _auto(ns.sizes, ns.ratio, ns.repeat)
    print(f"{'size':>6} {'it/s':>8} {'ms/it':>8} {'transforms ms':>14} {'prox ms':>8} {'it/transforms':>14}")
    for n in ns.sizes:
        scene = ImageTarget().render(Camera(resolution=n))
        acq = Simulator().acquire(scene, Zigzag(ns.ratio).select(n), n, np.random.default_rng(0))
        solver = FistaTVSolver(lam=0.02, max_iter=ns.iterations, tol=0.0)  # fixed weight: iterations only
        solver.solve(acq)  # warm-up
        t0 = time.perf_counter()
        out = solver.solve(acq)
        dt = time.perf_counter() - t0
        its = int(out.info["iterations"])
        op = hadamard_operator(n, acq.indices)
        x = np.random.default_rng(1).random(n * n)
        t_pair = median_time_s(lambda: op.rmatvec(op.matvec(x)), 7)
        img = x.reshape(n, n)
        t_prox = median_time_s(lambda: denoise_tv_chambolle(img, weight=0.02, eps=0.0, max_num_iter=solver.tv_iter), 7)
        per_it = dt / its
        print(
            f"{n:>4}^2 {its / dt:>8.1f} {per_it * 1e3:>8.2f} {t_pair * 1e3:>14.3f} {t_prox * 1e3:>8.2f} "
            f"{per_it / t_pair:>14.1f}"
        )
    return 0


def _auto(sizes: list[int], ratio: float, repeat: int) -> int:
    cases = {
        "free": forward_model(detector=IdealDetector()),
        "device": forward_model(illumination=Background(klux=15.0), detector=Photodiode()),
    }
    print(
        f"{'size':>6} {'case':>7} {'rule':>5} {'lam':>9} {'fwht ms':>8} {'auto ms':>8} {'fixed ms':>9} "
        f"{'auto/fwht':>10} {'choice/solve':>13}"
    )
    for n in sizes:
        scene = ImageTarget().render(Camera(resolution=n))
        for case, effects in cases.items():
            acq = Simulator(effects=effects).acquire(scene, Zigzag(ratio).select(n), n, np.random.default_rng(0))
            auto = FistaTVSolver()
            out = auto.solve(acq)
            fixed = FistaTVSolver(lam=float(out.info["lam"]))
            t_inv = median_time_s(lambda: FWHTSolver().solve(acq), repeat)
            t_auto = median_time_s(lambda: auto.solve(acq), repeat, min_time_s=0.0)
            t_fixed = median_time_s(lambda: fixed.solve(acq), repeat, min_time_s=0.0)
            print(
                f"{n:>4}^2 {case:>7} {out.info['lam_rule']!s:>5} {float(out.info['lam']):>9.2e} {t_inv * 1e3:>8.3f} "
                f"{t_auto * 1e3:>8.1f} {t_fixed * 1e3:>9.1f} {t_auto / t_inv:>10.0f} {t_auto / t_fixed - 1:>13.1f}"
            )
    return 0
