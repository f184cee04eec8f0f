"""A Ray executor behind the same `map(fn, items, description)` interface as LocalExecutor.

Without an address it starts (lazily, on the first `map`) a private local Ray cluster with
`workers` CPUs and no dashboard, and shuts it down again at `shutdown()` or interpreter exit;
with an address (`--ray-address`, e.g. "ray://head:10001" or "auto") it connects to that
cluster and never shuts it down. Workers import this checkout's packages: the repository root is
put first on the workers' PYTHONPATH, so a worktree wins over an editable install elsewhere.

Failures: a worker process that dies mid-item (OOM killer, segfault, node loss) is retried by
Ray itself (`max_retries`); an exception raised by `fn` is retried up to `exception_retries`
times, then `ItemFailed` names the item's position and value. Results come back in item order.
"""

from __future__ import annotations

import atexit
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import ray
from ray.exceptions import RayError, RayTaskError

from gst.cores import available_cores
from pipeline.errors import PROJECT_ROOT, ItemFailed, describe

ProgressFactory = Callable[..., Any]


def _worker_env(extra_path: Path) -> dict[str, str]:
    parts = [str(extra_path)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    # One thread per task: Ray schedules one task per CPU, so BLAS/OpenMP pools would oversubscribe.
    return {
        "PYTHONPATH": os.pathsep.join(dict.fromkeys(parts)),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
    }


def _call(fn: Callable[[Any], Any], item: Any) -> Any:
    return fn(item)


class RayExecutor:
    """Maps a function over items as Ray tasks (one CPU each), ordered results, with retries."""

    def __init__(
        self,
        workers: int | None = None,
        progress: ProgressFactory | None = None,
        *,
        address: str | None = None,
        max_retries: int = 3,
        exception_retries: int = 1,
    ):
        if max_retries < 0 or exception_retries < 0:
            raise ValueError(
                f"retries must be >= 0, got max_retries={max_retries}, "
                f"exception_retries={exception_retries}"
            )
        self.workers = max(1, workers or available_cores())
        self.address = address
        self.max_retries = max_retries
        self.exception_retries = exception_retries
        self._progress = progress
        self._started_cluster = False

    # -- cluster lifecycle ----------------------------------------------------------------------
    def _ensure_connected(self) -> None:
        if ray.is_initialized():
            return
        runtime_env = {"env_vars": _worker_env(PROJECT_ROOT)}
        common = {
            "logging_level": logging.WARNING,
            "log_to_driver": True,
            "runtime_env": runtime_env,
            "ignore_reinit_error": True,
        }
        if self.address:
            try:
                ray.init(address=self.address, **common)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise RuntimeError(
                    f"cannot connect to the Ray cluster at --ray-address {self.address!r}: {exc}"
                ) from exc
            return
        ray.init(num_cpus=self.workers, include_dashboard=False, **common)
        self._started_cluster = True
        atexit.register(self.shutdown)

    def shutdown(self) -> None:
        """Stop the local cluster this executor started (a cluster it connected to is left
        alone)."""
        if self._started_cluster and ray.is_initialized():
            ray.shutdown()
        self._started_cluster = False

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()

    # -- mapping --------------------------------------------------------------------------------
    def map(
        self, fn: Callable[[Any], Any], items: Iterable[Any], description: str = ""
    ) -> list[Any]:
        """`[fn(x) for x in items]`, computed as Ray tasks; raises ItemFailed naming the item."""
        items = list(items)
        if not items:
            return []
        self._ensure_connected()
        task = ray.remote(num_cpus=1, max_retries=self.max_retries, retry_exceptions=False)(_call)
        fn_ref = ray.put(fn)  # shipped once, not once per item
        results: list[Any] = [None] * len(items)
        attempts = [1] * len(items)
        pending: dict = {}

        def finished() -> Iterator[int]:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                ref = ready[0]
                i = pending.pop(ref)
                try:
                    results[i] = ray.get(ref)
                except RayTaskError as exc:
                    if attempts[i] <= self.exception_retries:
                        attempts[i] += 1
                        logging.getLogger("pipeline").warning(
                            "%s: item %d (%s) failed (%s); retrying (attempt %d of %d)",
                            description or "ray map",
                            i,
                            describe(items[i]),
                            _cause(exc),
                            attempts[i],
                            self.exception_retries + 1,
                        )
                        pending[task.remote(fn_ref, items[i])] = i
                        continue
                    self._cancel(pending)
                    raise ItemFailed(
                        f"{description or 'ray map'}: item {i} ({describe(items[i])}) failed "
                        f"after {attempts[i]} attempt(s): {_cause(exc)}"
                    ) from exc
                except (
                    RayError
                ) as exc:  # worker died more often than max_retries, or the node was lost
                    self._cancel(pending)
                    raise ItemFailed(
                        f"{description or 'ray map'}: item {i} ({describe(items[i])}) was lost: "
                        f"its worker died {self.max_retries + 1} time(s) ({type(exc).__name__}: "
                        f"{exc})"
                    ) from exc
                yield i

        try:
            for i, x in enumerate(items):  # inside: a Ctrl-C while submitting cancels them too
                pending[task.remote(fn_ref, x)] = i
            done = finished()
            if self._progress is not None:
                done = self._progress(done, description=description, total=len(items))
            for _ in done:
                pass
        except BaseException:
            # Ctrl-C (or SIGTERM) ends the map as a failed item does: the pending tasks are
            # cancelled. Left alone they ran on in a cluster given with --ray-address (only a
            # private cluster is shut down at exit), writing into the next run's staging folder.
            self._cancel(pending)
            raise
        return results

    @staticmethod
    def _cancel(pending: dict) -> None:
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 - best effort on the way to raising the real error
                pass
        pending.clear()


def _cause(exc: RayTaskError) -> str:
    cause = getattr(exc, "cause", None)
    return f"{type(cause).__name__}: {cause}" if cause is not None else str(exc).splitlines()[0]
