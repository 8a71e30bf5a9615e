"""Issue 36, target (a): would a guard that tests the completion's *extrapolation* catch the
checkerboard on ``basic``? A trial, not in the solver.

The tail of the acquisition order (the last tenth of the measured coefficients, the ones next to
the unmeasured ones in every order but ``random``) is predicted by the completion of the first nine
tenths (under the exponent the full data chose) and by zero (the white prior: zero-filling); the
``tail`` ratio is the first squared error over the second (> 1: zero-filling extrapolates better).
Printed beside the leave-one-out ratio of the shipped guard, noise-free. Designed after seeing the
held-out checkerboard; run here on it and on the 9 tuning images.

    python experiments/heldout/tail_guard.py checkerboard,chelsea,coffee,rocket,hubble_deep_field,retina,logo,colorwheel,lfw_subset,immunohistochemistry basic,zigzag 0.25
"""

from __future__ import annotations

import sys

import numpy as np

# the held-out benchmark's orders and simulators; a script's own folder is on sys.path
from heldout_cs import ORDERS, N, simulator

from nirspi_pipe.metrics import psnr
from nirspi_pipe.patterns.hadamard import fwht
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.common import checked_coefficients
from nirspi_pipe.solvers.completion import CompletionSolver, complete
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.types import Camera


def main() -> int:
    imgs, orders, ratio = sys.argv[1].split(","), sys.argv[2].split(","), float(sys.argv[3])
    sim = simulator("free")
    for o in orders:
        idx = ORDERS[o](ratio).select(N)
        m = idx.size
        k = max(1, m // 10)
        head, tail = np.arange(m - k), np.arange(m - k, m)
        for name in imgs:
            scene = ImageTarget(path=f"skimage:{name}").render(Camera(resolution=N))
            truth = sim.reference_image(scene)
            acq = sim.acquire(scene, idx, N, np.random.default_rng(0))
            y = checked_coefficients(acq, "completion")
            solver = CompletionSolver()
            done = solver.solve(acq)
            priors = [p for p in solver.priors() if p.alpha == done.info["alpha"]] or solver.priors()[1:2]
            x_head = complete(N, idx[head], y[head], 0.0, priors)[0]
            err = float(np.sum((fwht(x_head.ravel())[idx[tail]] - y[tail]) ** 2))
            white = float(np.sum(y[tail] ** 2))
            zero = zero_filled_inverse(N, idx, y)
            print(
                f"{o} {name}: completion {psnr(truth, done.data):.2f} dB, fwht {psnr(truth, zero):.2f} dB, "
                f"loo {done.info['loo_ratio']:.2f}, tail {err / white:.2f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
