"""Tracking scenes for the scale-out tests: walkers that never cross, one entering late and one
leaving early, so that tracking is unambiguous at any chunk border."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from gst.track import BoxDepthPredictor, SuppliedBoxes, TrackOptions
from gst.track.batch import VideoJob
from tests.track_synthetic import Walker, render, walker_boxes, write_boxes_csv, write_video

MODEL = {"name": "test-double", "version": "0"}
W, H = 320, 240


def separated_walkers() -> list[Walker]:
    return [
        Walker((40, 40, 220), (40.0, 130.0), (3.0, 0.0), (40.0, 100.0)),
        Walker((220, 80, 40), (280.0, 60.0), (-2.0, 0.5), (36.0, 90.0)),
        Walker((60, 200, 60), (160.0, 40.0), (0.5, 1.5), (30.0, 80.0)),
    ]


def write_clip(root: Path, name: str, frames: int) -> tuple[Path, Path]:
    """(video, boxes CSV) of `frames` frames; walker 2 enters at frame 23, walker 1 leaves at 47."""
    walkers = separated_walkers()
    boxes = walker_boxes(walkers, frames)
    visible = np.ones(boxes.shape[:2], bool)
    visible[:23, 2] = False
    visible[47:, 1] = False
    video = write_video(root / f"{name}.avi", render(walkers, boxes, W, H), W, H)
    return video, write_boxes_csv(root / f"{name}.csv", boxes, name, visible)


def job(video: Path, csv: Path, **kw) -> VideoJob:
    """A tracking job with supplied boxes and the pixel-free predictor (fast, deterministic)."""
    options = kw.pop("options", TrackOptions(frames_per_group=5, batch_size=4))
    detector = kw.pop("detector", functools.partial(SuppliedBoxes.from_file, csv, video.stem))
    predictor = kw.pop("predictor", BoxDepthPredictor)
    return VideoJob(video, detector, predictor, MODEL, name=video.stem, options=options, **kw)
