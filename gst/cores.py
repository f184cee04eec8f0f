"""How many CPU cores this process may use.

`os.cpu_count()` counts the machine's cores; a container or `taskset` may allow fewer, and
sizing thread pools and worker counts by the machine oversubscribes the allowed ones. The
process's CPU affinity is what it may run on (a CPU quota without a cpuset is not seen here)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["available_cores", "torch_threads"]


def available_cores() -> int:
    """Cores this process may run on (at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity on this platform (e.g. macOS)
        return max(1, os.cpu_count() or 1)


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """torch's intra-op threads set to `n` (None: unchanged) inside the block, put back after:
    an in-process caller shares the pool."""
    import torch

    before = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)
