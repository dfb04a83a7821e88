"""Helpers shared by the benchmarks (not a benchmark: ``benchmarks.run`` skips this module)."""

from __future__ import annotations

import time

import numpy as np


def median_seconds(fn, repeats: int = 3) -> float:
    """Median wall-clock seconds of ``repeats`` calls of ``fn()``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))
