"""Timing shared by the benchmark scripts (they put the repository root on sys.path)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def median_time(fn: Callable[[], T], repeats: int, warmup: int = 0) -> tuple[float, T]:
    """Median wall time in seconds of `repeats` calls of `fn`, and the last call's result;
    `warmup` untimed calls first (first-call costs: lazy imports, allocator, caches)."""
    for _ in range(warmup):
        fn()
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out
