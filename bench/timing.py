"""Timing helper shared by the benchmarks (``bench/run.py`` puts this folder on ``sys.path``)."""

from __future__ import annotations

import math
import time


def best_time(fn, repeats: int, warmup: bool = False) -> tuple[float, object]:
    """Fastest wall time (s) of ``repeats`` calls of ``fn`` (after one untimed call with ``warmup``)
    and the last result."""
    result = fn() if warmup else None
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result
