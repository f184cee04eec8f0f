"""Picklable item functions for the scale-out tests (workers import them as tests.scaleout_items)."""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class MarkedItem:
    """An item that writes one result file; `crash` items kill their worker the first time."""

    value: int
    out_dir: Path
    crash: str = ""  # "" | "kill" (SIGKILL own process) | "raise" (an exception)


def square_and_record(item: MarkedItem) -> int:
    """Square the value and append a line to its log, crashing the first time if asked to."""
    marker = item.out_dir / f"attempted-{item.value}"
    first_attempt = not marker.exists()
    marker.touch()
    with open(item.out_dir / f"log-{item.value}.txt", "a") as fh:  # one line per completed attempt
        if item.crash and first_attempt:
            if item.crash == "kill":
                os.kill(os.getpid(), signal.SIGKILL)
            raise RuntimeError(f"deliberate failure of item {item.value}")
        fh.write(f"{item.value}\n")
    return item.value * item.value


def always_fails(x: int) -> int:
    raise ValueError(f"bad item {x}")


def worker_pid(x: int) -> tuple[int, int]:
    return x, os.getpid()


class KillOnceDetector:
    """Supplied boxes that SIGKILL their own worker process at `kill_frame`, once (marker file)."""

    def __init__(self, csv: Path, video: str, marker: Path, kill_frame: int):
        from gst.track.detection import SuppliedBoxes

        self.inner = SuppliedBoxes.from_file(csv, video)
        self.marker, self.kill_frame = Path(marker), kill_frame

    def detect(self, image, frame_index: int):
        if frame_index == self.kill_frame and not self.marker.exists():
            self.marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.detect(image, frame_index)
