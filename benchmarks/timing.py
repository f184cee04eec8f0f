"""Timing shared by the benchmark scripts (they put the repository root on sys.path)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

from gst.eval.bench import round_robin_medians as round_robin

T = TypeVar("T")


def median_time(fn: Callable[[], T], repeats: int, warmup: int = 0) -> tuple[float, T]:
    """Median wall time in seconds of `repeats` calls of `fn`, and the last call's result;
    `warmup` untimed calls first (first-call costs: lazy imports, allocator, caches)."""
    return round_robin([fn], repeats, warmup=warmup)[0]  # type: ignore[return-value]


def round_robin_medians(
    calls: Sequence[Callable[[], T]], repeats: int, warmup: int = 1
) -> list[tuple[float, T]]:
    """(median wall seconds, last result) of each call over `repeats` rounds that call every one
    in turn; first `warmup` untimed calls of the first (`gst.eval.bench.round_robin_medians`)."""
    return round_robin(calls, repeats, warmup=warmup, warm_each=False)  # type: ignore[return-value]
