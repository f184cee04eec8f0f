"""Run an iterator in a background thread, a bounded number of items ahead.

OpenCV and numpy release the GIL in their heavy calls, so decoding and cropping the next frames
overlap with prediction and writing in the caller's thread. Exceptions raised by the iterator
are re-raised in the consumer, in order; closing the consumer stops the thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from typing import TypeVar

T = TypeVar("T")

_DONE = object()


class _Failure:
    def __init__(self, exc: BaseException):
        self.exc = exc


def background(items: Iterator[T], depth: int, name: str = "track-prefetch") -> Iterator[T]:
    """Yield what `items` yields, produced up to `depth` items ahead in a thread. A depth below
    1 is refused at the call (inside the generator it waited for the first `next`)."""
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    return _background(items, depth, name)


def _background(items: Iterator[T], depth: int, name: str) -> Iterator[T]:
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for item in items:
                if not put(item):
                    return
            put(_DONE)
        except BaseException as exc:  # handed to the consumer
            put(_Failure(exc))
        finally:
            close = getattr(items, "close", None)
            if close is not None:
                close()  # e.g. releases a video capture

    thread = threading.Thread(target=work, name=name, daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, _Failure):
                raise item.exc
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)
