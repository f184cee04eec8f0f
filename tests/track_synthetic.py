"""Synthetic scenes for the tracking tests: coloured 'people' (rectangles) moving on a textured
background, written as a real video with cv2.VideoWriter, with their true boxes; and tracking
them with the pixel-free test predictor."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gst.track import BoxDepthPredictor, TrackResult, track_video

W, H = 320, 240  # the crossing scene's frame size
MODEL = {"name": "test-double", "version": "0"}  # the test predictors' model identity in outputs


@dataclass(frozen=True)
class Walker:
    colour: tuple[int, int, int]  # BGR
    start: tuple[float, float]  # box centre (px) at frame 0
    velocity: tuple[float, float]  # px per frame
    size: tuple[float, float]  # box width, height (px)
    depth_order: int = 0  # higher is drawn in front


def walker_boxes(walkers: list[Walker], frames: int) -> np.ndarray:
    """(frames, people, 4) true boxes x0, y0, x1, y1 (corner convention), integer-aligned."""
    out = np.zeros((frames, len(walkers), 4))
    for i in range(frames):
        for k, w in enumerate(walkers):
            cx, cy = w.start[0] + w.velocity[0] * i, w.start[1] + w.velocity[1] * i
            out[i, k] = np.round(
                [cx - w.size[0] / 2, cy - w.size[1] / 2, cx + w.size[0] / 2, cy + w.size[1] / 2]
            )
    return out


def background(width: int, height: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.integers(60, 120, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
    return cv2.resize(noise, (width, height), interpolation=cv2.INTER_LINEAR)


def render(walkers: list[Walker], boxes: np.ndarray, width: int, height: int, seed: int = 0):
    """Yield BGR frames: each walker a filled box with a darker 'head' band."""
    bg = background(width, height, seed)
    order = np.argsort([w.depth_order for w in walkers])
    for i in range(len(boxes)):
        f = bg.copy()
        for k in order:
            x0, y0, x1, y1 = boxes[i, k].astype(int)
            colour = walkers[k].colour
            cv2.rectangle(f, (x0, y0), (x1 - 1, y1 - 1), colour, -1)
            head = tuple(int(c * 0.6) for c in colour)
            cv2.rectangle(f, (x0, y0), (x1 - 1, y0 + (y1 - y0) // 6), head, -1)
        yield f


def write_video(
    path: Path, frames, width: int, height: int, fps: float = 30.0, fourcc: str = "MJPG"
) -> Path:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (width, height))
    if not vw.isOpened():
        raise RuntimeError(f"cannot write {path} with {fourcc}")
    for f in frames:
        vw.write(f)
    vw.release()
    return path


def write_boxes_csv(
    path: Path, boxes: np.ndarray, video: str, visible: np.ndarray | None = None
) -> Path:
    """One CSV row per visible true box (no ids: the tracker must find them)."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["video", "frame", "x0", "y0", "x1", "y1", "score"])
        for i in range(boxes.shape[0]):
            for k in range(boxes.shape[1]):
                if visible is None or visible[i, k]:
                    w.writerow([video, i, *boxes[i, k].tolist(), 0.9])
    return path


def crossing_scene(frames: int = 40, width: int = 320, height: int = 240) -> list[Walker]:
    """Two people crossing in opposite directions plus one walking down: their boxes overlap."""
    return [
        Walker((40, 40, 220), (40.0, 130.0), (6.0, 0.0), (40.0, 100.0), depth_order=2),
        Walker((220, 80, 40), (280.0, 125.0), (-6.0, 0.0), (36.0, 90.0), depth_order=1),
        Walker((60, 200, 60), (160.0, 40.0), (0.5, 3.0), (30.0, 80.0), depth_order=0),
    ]


def crossing_clip(
    folder: Path, frames: int, width: int = W, height: int = H
) -> tuple[list[Walker], np.ndarray, Path]:
    """The crossing scene written as `folder`/clip.avi: (walkers, true boxes, video path)."""
    walkers = crossing_scene(frames, width, height)
    boxes = walker_boxes(walkers, frames)
    video = write_video(folder / "clip.avi", render(walkers, boxes, width, height), width, height)
    return walkers, boxes, video


def track_boxes(video: Path, out: Path, detector, **kwargs) -> TrackResult:
    """`track_video` with the pixel-free BoxDepthPredictor (the whole loop but the network) and
    the test model identity; `kwargs` go to `track_video`."""
    kwargs.setdefault("model", MODEL)
    return track_video(video, out, detector, BoxDepthPredictor(), **kwargs)
