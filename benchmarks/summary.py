"""Means shared by the benchmark scripts' summaries (they put the repository root on sys.path):
what a mean leaves out is counted, never averaged in as 0 or NaN."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np


def finite_mean(values) -> tuple[float, int]:
    """(mean of the finite values, NaN when there are none; how many were left out as NaN or
    infinite)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    ok = np.isfinite(v)
    return (float(v[ok].mean()) if ok.any() else math.nan), int((~ok).sum())


def known_mean(values: Iterable[float | None]) -> tuple[float, int]:
    """(mean of the values that are not None, NaN when all are; how many were None)."""
    values = list(values)
    known = [float(v) for v in values if v is not None]
    return (sum(known) / len(known) if known else math.nan), len(values) - len(known)


def weighted_mean(pairs: Iterable[tuple[float | None, float]]) -> float:
    """sum(value * weight) / sum(weight) over the (value, weight) pairs whose value is not None
    (NaN when their weights sum to 0): a value's weight counts only where the value does."""
    total = weight = 0.0
    for value, w in pairs:
        if value is not None:
            total += value * w
            weight += w
    return total / weight if weight > 0 else math.nan


def left_out(count: int, of: int, what: str) -> str:
    """'' when nothing was left out, else ' (COUNT of OF WHAT left out)'."""
    return f" ({count} of {of} {what} left out)" if count else ""
