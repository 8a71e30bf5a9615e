"""``nirspi-bench transform``: our 2D Hadamard transform against numpy's ``fft2``.

Both run on the same real ``n × n`` float64 array in the same process; the ratio
``fwht2 / fft2`` below 1 means ours is faster. Target: ratio ≤ 1 at every size.
"""

from __future__ import annotations

import argparse

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.patterns.hadamard import fwht2, ifwht2


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench transform", description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512])
    parser.add_argument("--repeat", type=int, default=15)
    ns = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"{'size':>6} {'fwht2 ms':>10} {'fft2 ms':>10} {'ratio':>7} {'inverse err':>12}")
    worst = 0.0
    for n in ns.sizes:
        a = rng.random((n, n))
        t_ours = median_time_s(lambda: fwht2(a), ns.repeat)
        t_fft = median_time_s(lambda: np.fft.fft2(a), ns.repeat)
        err = float(np.max(np.abs(ifwht2(fwht2(a)) - a)))
        ratio = t_ours / t_fft
        worst = max(worst, ratio)
        print(f"{n:>4}^2 {t_ours * 1e3:>10.3f} {t_fft * 1e3:>10.3f} {ratio:>7.2f} {err:>12.1e}")
    print(f"worst ratio fwht2/fft2 = {worst:.2f} ({'meets' if worst <= 1.0 else 'misses'} target <= 1)")
    return 0
