"""``nirspi-bench fista``: FISTA-TV iterations per second, against its own floor.

One FISTA iteration is a forward and an adjoint fast transform (the gradient) plus a TV
proximal step. The peers, timed in the same run on the same image: the transform pair alone
(the floor of any iterative solver here) and the TV prox alone (scikit-image Chambolle).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from skimage.restoration import denoise_tv_chambolle

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.common import hadamard_operator
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.types import Camera


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench fista", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128])
    parser.add_argument("--ratio", type=float, default=0.25)
    parser.add_argument("--iterations", type=int, default=50)
    ns = parser.parse_args(argv)
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
