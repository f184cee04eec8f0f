"""Frames from a video file or an image folder, with subsampling.

An image folder is read in natural filename order (`img2.png` before `img10.png`); frame `i` is
the i-th image. Frames of different cameras are matched by index, so folders of synchronised
cameras must hold the same instants in the same order.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from gst.video import VideoError, probe_video
from gst.video import iter_frames as video_frames

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


class FrameSourceError(VideoError):
    """A video or image folder cannot be read."""


def _natural_key(path: Path):
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def list_images(folder: Path) -> list[Path]:
    """Image files in a folder, in natural filename order; hidden files are left out (macOS
    writes a `._img1.png` beside every image on a FAT/exFAT card: not an image, and read as
    one it stopped the folder with "cannot read image" and shifted every frame index)."""
    files = [
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
    ]
    if not files:
        raise FrameSourceError(
            f"image folder '{folder}' holds no images ({', '.join(IMAGE_SUFFIXES)})"
        )
    return sorted(files, key=_natural_key)


def numbering_gap(files: list[Path]) -> str | None:
    """Where the numbers at the end of the files' names (frame_000123.png) stop going up in one
    step, said in words; None when they do, or when the names carry no such number. A frame
    is the i-th image, so one missing file puts the camera out of step from there on."""
    numbers = []
    for p in files:
        m = re.search(r"(\d+)\D*$", p.stem)
        if m is None:
            return None
        numbers.append(int(m.group(1)))
    steps = np.diff(numbers)
    if len(steps) == 0 or ((steps == steps[0]).all() and steps[0] > 0):
        return None
    usual = np.median(steps)
    odd = np.flatnonzero((steps != usual) | (steps <= 0))
    i = int(odd[0]) if len(odd) else 0
    return f"'{files[i].name}' is followed by '{files[i + 1].name}'"


def _probe(path: Path):
    try:
        return probe_video(path)
    except VideoError as exc:
        raise FrameSourceError(str(exc)) from None


def _check_exists(source: Path) -> None:
    if not source.exists():
        raise FrameSourceError(
            f"frame source '{source}' does not exist (expected a video or image folder)"
        )


def count_frames(source: str | Path) -> int:
    """Number of frames in a video (as the container reports it) or images in a folder."""
    source = Path(source)
    _check_exists(source)
    if source.is_dir():
        return len(list_images(source))
    return _probe(source).frames


def source_image_size(source: str | Path) -> tuple[int, int]:
    """(width, height) of the frames of a video or of the first image in a folder."""
    source = Path(source)
    _check_exists(source)
    if source.is_dir():
        first = list_images(source)[0]
        # as `iter_frames` reads it: IMREAD_UNCHANGED ignored a phone photo's EXIF rotation,
        # so the camera got its width and height swapped
        img = cv2.imread(str(first), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FrameSourceError(f"cannot read image '{first}'")
        return int(img.shape[1]), int(img.shape[0])
    info = _probe(source)
    return info.width, info.height


def _to_8bit(img: np.ndarray, path: Path) -> np.ndarray:
    """A 16-bit image shifted down by the bits its values use (at least 8): full-range 16-bit
    images as OpenCV converts them, 12-bit data in a 16-bit file shifted by 4, not 8."""
    if img.dtype == np.uint8:
        return img
    if img.dtype != np.uint16:
        raise FrameSourceError(
            f"image '{path}' holds {img.dtype} pixels; expected 8- or 16-bit integer images"
        )
    bits = max(8, int(img.max()).bit_length())
    return (img >> (bits - 8)).astype(np.uint8)


def iter_frames(
    source: str | Path, frame_step: int = 1, max_frames: int | None = None, grayscale: bool = True
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, image) for every `frame_step`-th frame, at most `max_frames` of them.

    Video frames that are skipped are grabbed but not decoded to images, which is cheaper.
    """
    source = Path(source)
    _check_exists(source)
    step = max(int(frame_step), 1)
    limit = None if max_frames is None else max(int(max_frames), 0)
    # ANYDEPTH: OpenCV's own 16-to-8-bit conversion keeps the top 8 bits, and a machine-vision
    # camera's 10- or 12-bit frames saved as 16-bit images (0..4095) came out black (0..15)
    flag = (cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR) | cv2.IMREAD_ANYDEPTH
    yielded = 0
    size = None
    if source.is_dir():
        files = list_images(source)
        if (gap := numbering_gap(files)) is not None:
            log.warning(
                "image folder '%s': the numbers in the file names skip (%s); frame i is the "
                "i-th image, so this camera is out of step with the others from there on "
                "unless theirs skip alike",
                source, gap,
            )  # fmt: skip
        for index, path in enumerate(files):
            if index % step:
                continue
            if limit is not None and yielded >= limit:
                return
            img = cv2.imread(str(path), flag)
            if img is None:
                raise FrameSourceError(f"cannot read image '{path}'")
            img = _to_8bit(img, path)
            if size is None:
                size = img.shape[:2]
            elif img.shape[:2] != size:  # one camera's images: a portrait shot among landscape
                raise FrameSourceError(
                    f"image '{path}' is {img.shape[1]}x{img.shape[0]}, the folder's first "
                    f"{size[1]}x{size[0]}: one camera's images must share a size (EXIF "
                    "rotation applied)"
                )
            yielded += 1
            yield index, img
        return
    _probe(source)
    for frame in video_frames(source, stride=step):
        if limit is not None and yielded >= limit:
            return
        img = frame.image
        if grayscale and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        yielded += 1
        yield frame.index, img
