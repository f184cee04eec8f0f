"""Reading camera videos frame by frame, with checks that name the file at fault.

OpenCV's `VideoCapture` fails quietly (an unreadable file just yields no frames), so every entry
point here checks what it got and raises `VideoError` naming the camera and the path.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


class VideoError(ValueError):
    """A video cannot be read, or does not match the rig or the other cameras."""


@dataclass(frozen=True)
class VideoInfo:
    """What a video file says about itself (from its container, then checked by decoding)."""

    camera: str
    path: Path
    frames: int
    width: int
    height: int
    fps: float


def probe_video(path: Path | str, camera: str = "") -> VideoInfo:
    """Open a video, decode its first frame and return its size, frame count and rate.

    Raises `VideoError` naming the camera and file if it is missing, unreadable or empty.
    """
    path = Path(path)
    who = f"camera '{camera}' video {path}" if camera else f"video {path}"
    if not path.is_file():
        raise VideoError(f"{who}: file not found")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise VideoError(f"{who}: OpenCV cannot open it (not a video, or an unsupported codec)")
        ok, frame = cap.read()
        if not ok or frame is None:
            raise VideoError(f"{who}: no frame could be decoded (corrupt or empty video)")
        frames = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    if frames <= 0:
        raise VideoError(f"{who}: the container reports {frames} frames")
    h, w = frame.shape[:2]
    return VideoInfo(camera=camera, path=path, frames=frames, width=w, height=h, fps=fps)


def check_videos(
    videos: dict[str, Path], rig_names: Sequence[str], rig_sizes: dict[str, tuple[int, int]]
) -> dict[str, VideoInfo]:
    """Probe every camera's video and check them against the rig and against each other.

    `rig_sizes` maps camera name to (width, height). Errors name the camera and file: a video
    whose camera is not in the rig, an image size that differs from the calibration, or frame
    counts that differ across cameras (the cameras must be synchronised frame for frame).
    """
    if not videos:
        raise VideoError("no videos given: expected a mapping camera name -> video file")
    missing = [name for name in videos if name not in rig_names]
    if missing:
        raise VideoError(
            f"camera(s) {missing} have videos ({', '.join(str(videos[m]) for m in missing)}) "
            f"but are missing from the rig (rig cameras: {list(rig_names)})"
        )
    infos = {name: probe_video(path, name) for name, path in videos.items()}
    for name, info in infos.items():
        w, h = rig_sizes[name]
        if (info.width, info.height) != (w, h):
            raise VideoError(
                f"camera '{name}' video {info.path}: frames are {info.width}x{info.height}, but the "
                f"rig calibrates this camera at {w}x{h}"
            )
    counts = {name: info.frames for name, info in infos.items()}
    if len(set(counts.values())) > 1:
        detail = ", ".join(f"{n}: {c} ({infos[n].path.name})" for n, c in counts.items())
        raise VideoError(
            f"videos have different frame counts across cameras ({detail}); "
            "expected synchronised videos of equal length"
        )
    return infos


def read_frames(
    path: Path | str, frames: Sequence[int], camera: str = "", scale: float = 1.0
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, BGR image) for the sorted frame indices in `frames`.

    Decodes sequentially and skips unwanted frames with `grab` (cheaper than seeking in
    compressed video). With `scale` < 1 the frames are shrunk with area averaging. Raises
    `VideoError` naming the file if the video ends before a requested frame.
    """
    wanted = sorted(set(int(f) for f in frames))
    if not wanted:
        return
    path = Path(path)
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise VideoError(f"camera '{camera}' video {path}: OpenCV cannot open it")
    try:
        pos = 0
        for f in wanted:
            while pos < f:
                if not cap.grab():
                    raise VideoError(
                        f"camera '{camera}' video {path}: ended at frame {pos}, "
                        f"but frame {f} was requested"
                    )
                pos += 1
            ok, image = cap.read()
            if not ok or image is None:
                raise VideoError(
                    f"camera '{camera}' video {path}: frame {f} could not be decoded "
                    "(truncated or corrupt video)"
                )
            pos += 1
            if scale != 1.0:
                size = scaled_size(image.shape[1], image.shape[0], scale)
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            yield f, image
    finally:
        cap.release()


def scaled_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Work-image size for a scale factor. Pixel centres map as u_work = (u + 0.5) * sx - 0.5
    with sx = width_work / width (OpenCV's resize convention)."""
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))
