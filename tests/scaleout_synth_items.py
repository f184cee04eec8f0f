"""Picklable wrappers for the synth fan-out tests (workers import them as
tests.scaleout_synth_items)."""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class DieOnceMidShare:
    """Calls `fn(job)`, except that the first attempt at the job rendering camera `camera` leaves
    a half-written video behind (as a worker killed mid-write would) and SIGKILLs its own
    process."""

    fn: Any
    marker_dir: Path
    camera: int

    def __call__(self, job):
        marker = self.marker_dir / f"died-{self.camera}"
        if self.camera in job.cameras and not marker.exists():
            marker.touch()
            stale = job.out_dir / "videos" / ".00_00.tmp.mp4"
            stale.parent.mkdir(parents=True, exist_ok=True)
            stale.write_bytes(b"half a video")
            os.kill(os.getpid(), signal.SIGKILL)
        return self.fn(job)
