"""Console output, progress bars and the per-run log file."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from rich.console import Console
from rich.logging import RichHandler
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from pipeline.errors import TRACEBACK_LOGGER

LOGGER_NAME = "pipeline"


def make_console(quiet: bool, stderr: bool = True) -> Console:
    """Logs and progress go to stderr; a command's own output (the `stages` listing) to stdout."""
    return Console(stderr=stderr, quiet=quiet)


def setup_logging(console: Console, log_dir: Path | None, command: str, quiet: bool) -> Path | None:
    """Console handler (rich, unless quiet) plus one log file per run under `log_dir`."""
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for h in list(root.handlers):
        root.removeHandler(h)
    if not quiet:
        handler = RichHandler(console=console, show_path=False, markup=False, rich_tracebacks=False)
    else:  # warnings still reach the user (a stale stage kept); errors print_error says
        handler = RichHandler(
            console=Console(stderr=True), show_path=False, markup=False, rich_tracebacks=False
        )
        handler.setLevel(logging.WARNING)
        handler.addFilter(lambda record: record.levelno < logging.ERROR)
    handler.addFilter(lambda record: record.name != TRACEBACK_LOGGER)
    root.addHandler(handler)
    log_path = None
    if log_dir is not None:
        log_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        log_path = log_dir / f"{stamp}-{command}.log"
        fh = logging.FileHandler(log_path)
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(fh)
    for noisy in ("matplotlib", "PIL", "h5py", "numexpr"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    return log_path


LOG_INTERVAL_S = 2.0  # the least time between two progress lines of one loop in a log file


class ProgressBars:
    """`bars(iterable, description=..., total=...)` yields items while showing a rich bar.
    Disabled (plain iteration) when quiet or when stderr is not a terminal, in which case a
    log line is written every ~10% (at most one per LOG_INTERVAL_S, and the last) so long runs
    still show signs of life in log files."""

    def __init__(self, console: Console, enabled: bool):
        self.console = console
        self.enabled = enabled and console.is_terminal

    def __call__(
        self, items: Iterable, description: str = "", total: int | None = None
    ) -> Iterator:
        if total is None:
            try:
                total = len(items)  # type: ignore[arg-type]
            except TypeError:
                total = None
        if not self.enabled:
            yield from self._logged(items, description, total)
            return
        columns = [
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
        ]
        with Progress(*columns, console=self.console, transient=True) as progress:
            task = progress.add_task(description, total=total)
            for item in items:
                yield item
                progress.advance(task)

    @staticmethod
    def _logged(items, description, total, min_interval_s: float = LOG_INTERVAL_S) -> Iterator:
        """A line at every tenth of the way, at most one per `min_interval_s`, and the last:
        a 0.3 s step wrote ten lines ("people per view: 40/400 (0.0 s)" ...)."""
        log = logging.getLogger(LOGGER_NAME)
        step = max(1, (total or 0) // 10)
        start = last = time.perf_counter()
        for i, item in enumerate(items, 1):
            yield item
            if not total:
                continue
            now = time.perf_counter()
            if i == total or (i % step == 0 and now - last >= min_interval_s):
                log.info("%s: %d/%d (%.1f s)", description, i, total, now - start)
                last = now


def print_error(console: Console, message: str) -> None:
    # Errors are shown even in quiet mode.
    Console(stderr=True).print(
        Text("error: ", style="bold red") + Text(message), highlight=False, soft_wrap=True
    )
    sys.stderr.flush()
