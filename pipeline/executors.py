"""Executors map a function over independent items (cameras, clips, frame chunks).

`executor.map(fn, items, description=...)` returns results in item order. `fn` and the items
must be picklable (module-level functions, plain data) because workers are processes. The
local executor uses a spawn-based process pool sized to the cores; a Ray executor plugs in
behind the same interface.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import traceback
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from gst.cores import available_cores
from pipeline.errors import ConfigError, ItemFailed, describe


class Executor(Protocol):
    workers: int

    def map(
        self, fn: Callable[[Any], Any], items: Iterable[Any], description: str = ""
    ) -> list[Any]: ...


ProgressFactory = Callable[..., Any]

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Worker initializer: the kernel sends SIGKILL to this worker when its parent dies (Linux
    prctl PR_SET_PDEATHSIG), so a killed run leaves no orphans that collide with the next run.
    A parent that died before this ran is caught by comparing pids."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the pid check below still helps
        pass
    if os.getppid() != parent_pid:
        os._exit(1)


class _Portable:
    """`fn` run in a worker so that its error reaches the parent: an exception that pickles but
    cannot be rebuilt there (a custom `__init__(self, a, b)` without `__reduce__`) broke the
    pool, and the map blamed a killed worker, losing the message. Such an error comes back as
    ItemFailed with its type, message and traceback in words."""

    def __init__(self, fn: Callable):
        self.fn = fn

    def __call__(self, item):
        try:
            return self.fn(item)
        except Exception as exc:
            try:
                pickle.loads(pickle.dumps(exc))
            except Exception:
                trace = "".join(traceback.format_exception(exc)).rstrip()
                raise ItemFailed(f"{type(exc).__name__}: {exc}\n{trace}") from None
            raise


class LocalExecutor:
    """Runs items in a process pool (or inline for one worker or one item)."""

    def __init__(self, workers: int | None = None, progress: ProgressFactory | None = None):
        self.workers = max(1, workers or available_cores())
        self._progress = progress

    def map(self, fn, items, description: str = "") -> list:
        items = list(items)
        if self.workers == 1 or len(items) <= 1:
            it = (
                items
                if self._progress is None
                else self._progress(items, description=description, total=len(items))
            )
            inline: list = []
            for i, x in enumerate(it):
                try:
                    inline.append(fn(x))
                except Exception as exc:  # named as the pool names it (`--workers 1` did not)
                    exc.add_note(f"{description or 'map'}: item {i} ({describe(items[i])})")
                    raise
            return inline
        results: list = [None] * len(items)
        ctx = mp.get_context("spawn")  # fork is unsafe with torch/OpenMP threads
        pool = ProcessPoolExecutor(
            max_workers=min(self.workers, len(items)),
            mp_context=ctx,
            initializer=die_with_parent,
            initargs=(os.getpid(),),
        )
        futures: dict = {}
        try:
            for i, x in enumerate(items):  # inside: a Ctrl-C while submitting stops it too
                futures[pool.submit(_Portable(fn), x)] = i
            done_iter: Iterable = as_completed(futures)
            if self._progress is not None:
                done_iter = self._progress(done_iter, description=description, total=len(items))
            for fut in done_iter:
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except BrokenProcessPool as exc:  # a worker killed (out of memory, a signal)
                    raise ItemFailed(
                        f"{description or 'map'}: a worker process died (killed, or out of "
                        f"memory?) with item {i} ({describe(items[i])}) among those unfinished"
                    ) from exc
                except Exception as exc:
                    exc.add_note(f"{description or 'map'}: item {i} ({describe(items[i])})")
                    raise
        except BaseException:
            # The first failure, or Ctrl-C, ends the map: the queued items are cancelled and
            # the running ones stopped. (A `with` pool's exit waited for every item: its
            # shutdown undid the cancel, and a Ctrl-C while waiting skipped it; 8 items on 2
            # workers ran to the end after the error, or after the interrupt.)
            _stop(pool, futures)
            raise
        pool.shutdown(wait=True)
        return results


def _stop(pool: ProcessPoolExecutor, futures) -> None:
    """Cancel a pool's queued items and end its worker processes (their writes are atomic, and
    a failed stage's staging folder is kept for the next run)."""
    for fut in futures:
        fut.cancel()
    # the pool keeps no public list of its processes (CPython 3.10-3.13 keep `_processes`, a
    # dict until shutdown); without it the queue is still cancelled and the workers finish
    # their current item
    workers = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in workers:
        if proc.is_alive():
            proc.terminate()
    for proc in workers:
        proc.join(timeout=5)


def make_executor(
    kind: str,
    workers: int | None,
    progress: ProgressFactory | None = None,
    ray_address: str | None = None,
) -> Executor:
    if kind == "local":
        return LocalExecutor(workers, progress)
    if kind == "ray":
        try:
            from pipeline.ray_executor import RayExecutor  # optional 'dist' extra
        except ImportError as exc:
            raise ConfigError(
                f"the Ray executor is unavailable ({exc}): install the 'dist' extra "
                '(pip install -e ".[dist]") or use --executor local'
            ) from None
        return RayExecutor(workers, progress, address=ray_address)
    raise ValueError(f"unknown executor kind '{kind}' (expected 'local' or 'ray')")


def chunks(seq: Sequence, size: int) -> list[Sequence]:
    """Split a sequence into consecutive chunks of at most `size` items."""
    if size < 1:  # `max(1, size)` in the step alone gave empty chunks: every item was lost
        raise ValueError(f"chunks: size must be >= 1, got {size}")
    return [seq[i : i + size] for i in range(0, len(seq), size)]
