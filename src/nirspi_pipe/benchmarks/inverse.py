"""``nirspi-bench inverse``: the zero-filled fast inverse against a dense ``scipy.linalg.hadamard``
product, on the same undersampled acquisition.

The dense reference builds ``H_N`` (``N = n²``) once, outside the timing, and computes
``H_N[:, idx] c / N``; it only fits in memory for small ``n`` (``N × N`` float64: 128 MiB at
``n = 64``). Ratio ``fast / dense`` below 1 means the fast inverse wins.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.linalg import hadamard

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.solvers.fwht import zero_filled_inverse


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench inverse", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64])
    parser.add_argument("--ratio", type=float, default=0.25)
    parser.add_argument("--repeat", type=int, default=9)
    ns = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"{'size':>6} {'fast ms':>10} {'dense ms':>10} {'ratio':>8} {'max diff':>9}")
    for n in ns.sizes:
        if n > 64:
            print(f"{n:>4}^2 skipped: the dense H_N would need {(n * n) ** 2 * 8 / 2**30:.0f} GiB")
            continue
        idx = Zigzag(ns.ratio).select(n)
        c = rng.standard_normal(idx.size)
        h = hadamard(n * n).astype(np.float64)  # the natural Sylvester order, like ours
        sub = np.ascontiguousarray(h[:, idx])
        t_fast = median_time_s(lambda: zero_filled_inverse(n, idx, c), ns.repeat)
        t_dense = median_time_s(lambda: sub @ c / (n * n), ns.repeat)
        diff = float(np.max(np.abs(zero_filled_inverse(n, idx, c).ravel() - sub @ c / (n * n))))
        print(f"{n:>4}^2 {t_fast * 1e3:>10.3f} {t_dense * 1e3:>10.3f} {t_fast / t_dense:>8.3f} {diff:>9.1e}")
        h = sub = np.empty(0)  # free the dense matrix before the next size
    return 0
