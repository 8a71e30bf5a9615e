"""Benchmarks run by ``nirspi-bench NAME``; each module defines ``main(argv) -> int``."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = ["median_time_s"]


def median_time_s(fn: Callable[[], object], repeat: int = 15, min_time_s: float = 0.02) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeat`` samples; each sample loops ``fn``
    enough times to last at least ``min_time_s`` (so fast calls are not timer noise)."""
    fn()  # warm-up (imports, caches, JIT)
    loops = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(loops):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time_s or loops >= 1 << 20:
            break
        loops *= 2
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(loops):
            fn()
        samples.append((time.perf_counter() - t0) / loops)
    return float(np.median(samples))
