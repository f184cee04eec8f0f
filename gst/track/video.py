"""Streaming video decode with OpenCV: frame stride, time range, exact start frame, prefetch.

Frame i has time i / fps (constant frame rate assumed; the container's fps is used). Frames in
[start_s, end_s) are read, every `stride`-th one counted from the first. Skipped frames are
grabbed without being converted. A file that opens but stops decoding before the frame count it
announces is reported as truncated or corrupt, naming the file and the frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gst.track.background import background

# A container's frame count can be an estimate; a shortfall of at most this many frames at the
# very end is taken as the real end rather than as truncation.
END_SLACK_FRAMES = 2


class VideoError(RuntimeError):
    """A video cannot be opened or decoded; the message names the file."""


class VideoTruncatedError(VideoError):
    """Decoding stopped before the announced end; `frame` is the first frame that failed."""

    def __init__(self, message: str, frame: int):
        super().__init__(message)
        self.frame = frame


@dataclass(frozen=True)
class VideoInfo:
    path: str
    width: int
    height: int
    fps: float
    frame_count: int | None  # None when the container does not say

    @property
    def name(self) -> str:
        return Path(self.path).stem

    @property
    def duration_s(self) -> float | None:
        return None if self.frame_count is None else self.frame_count / self.fps


@dataclass(frozen=True)
class Frame:
    index: int
    time_s: float
    image: np.ndarray  # (H, W, 3) uint8 BGR


def _open(path: str | Path) -> cv2.VideoCapture:
    path = Path(path)
    if not path.is_file():
        raise VideoError(f"{path}: video file not found")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise VideoError(
            f"{path}: cannot open as a video (corrupt, truncated or unsupported codec)"
        )
    return cap


def probe_video(path: str | Path) -> VideoInfo:
    """Size, fps and frame count of a video; raises VideoError naming the file."""
    cap = _open(path)
    try:
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    if w <= 0 or h <= 0:
        raise VideoError(f"{path}: reports no frame size ({w}x{h}); not a video stream")
    if not math.isfinite(fps) or fps <= 0:
        raise VideoError(
            f"{path}: reports no frame rate (fps = {fps}); cannot assign times to frames"
        )
    return VideoInfo(str(path), w, h, fps, n if n > 0 else None)


def frame_range(
    info: VideoInfo, start_s: float | None = None, end_s: float | None = None
) -> tuple[int, int | None]:
    """[first, end) frame indices covering times [start_s, end_s); end is None for 'to the end'."""
    eps = 1e-9
    first = 0 if start_s is None else max(0, math.ceil(start_s * info.fps - eps))
    end = None if end_s is None else max(0, math.ceil(end_s * info.fps - eps))
    if info.frame_count is not None:
        end = info.frame_count if end is None else min(end, info.frame_count)
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise ValueError(f"{info.path}: time range end {end_s} s must be after start {start_s} s")
    return first, end


def _decode(info: VideoInfo, first: int, end: int | None, stride: int) -> Iterator[Frame]:
    if end is not None and first >= end:
        return
    cap = _open(info.path)
    try:
        if first > 0:
            cap.set(cv2.CAP_PROP_POS_FRAMES, first)
            pos = int(cap.get(cv2.CAP_PROP_POS_FRAMES))
            if pos != first:
                raise VideoError(f"{info.path}: cannot seek to frame {first} (decoder is at {pos})")
        index = first
        while end is None or index < end:
            ok, image = cap.read()
            if not ok or image is None:
                short = None if info.frame_count is None else info.frame_count - index
                if short is None or short <= END_SLACK_FRAMES:
                    return
                raise VideoTruncatedError(
                    f"{info.path}: decoding failed at frame {index} of {info.frame_count} announced "
                    f"(file truncated or corrupt); frames before {index} decoded fine",
                    index,
                )
            yield Frame(index, index / info.fps, image)
            for _ in range(stride - 1):
                index += 1
                if (end is not None and index >= end) or not cap.grab():
                    return
            index += 1
    finally:
        cap.release()


def iter_frames(
    path: str | Path,
    *,
    stride: int = 1,
    start_s: float | None = None,
    end_s: float | None = None,
    start_frame: int | None = None,
    end_frame: int | None = None,
    prefetch: int = 0,
) -> Iterator[Frame]:
    """Yield frames first, first + stride, ... within [start_s, end_s).

    `start_frame` (used to resume, or to start a chunk) overrides the first frame; it must lie on
    the stride grid. `end_frame` (exclusive) stops earlier than `end_s` (a chunk's end).
    `prefetch` > 0 decodes that many frames ahead in a thread.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    info = probe_video(path)
    first, end = frame_range(info, start_s, end_s)
    if start_frame is not None:
        if start_frame < first or (start_frame - first) % stride:
            raise ValueError(
                f"{path}: start_frame {start_frame} is not on the grid {first} + k * {stride}"
            )
        first = start_frame
    if end_frame is not None:
        end = end_frame if end is None else min(end, end_frame)
    frames = _decode(info, first, end, stride)
    return background(frames, prefetch, name="video-decode") if prefetch > 0 else frames
