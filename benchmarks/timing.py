"""Timing shared by the benchmark scripts (they put the repository root on sys.path)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
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


def round_robin_medians(
    calls: Sequence[Callable[[], T]], repeats: int, warmup: int = 1
) -> list[tuple[float, T]]:
    """(median wall seconds, last result) of each call over `repeats` rounds that call every one
    in turn, so load from other processes falls on all of them alike; first `warmup` untimed
    calls of the first (first-call costs: lazy imports, allocator, caches, the page cache)."""
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    for _ in range(warmup if calls else 0):
        calls[0]()
    times: list[list[float]] = [[] for _ in calls]
    out: list = [None] * len(calls)
    for _ in range(repeats):
        for k, fn in enumerate(calls):
            t0 = time.perf_counter()
            out[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return [(statistics.median(t), o) for t, o in zip(times, out, strict=True)]
