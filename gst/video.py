"""Reading videos, the one module every package uses, with errors that name the file at fault.

OpenCV's `VideoCapture` fails quietly (an unreadable file just yields no frames), so every entry
point here checks what it got and raises `VideoError` naming the camera and the path.

- `probe_video(path)`: size, rate and frame count (`strict=True` also decodes the first frame
  and requires a frame count: what multi-camera extraction needs).
- `check_videos(...)`: every camera's video against the rig and the other cameras.
- `read_frames(path, frames)`: chosen frame indices, in order (skipped ones are only grabbed).
- `iter_frames(path, stride=..., start_s=..., end_s=...)`: a stream with times, an exact start
  frame (to resume or start a chunk) and optional prefetch in a thread.

Frame i has time i / fps (constant frame rate assumed; the container's fps is used). A file that
opens but stops decoding before the frame count it announces is reported as truncated or
corrupt, naming the file and the frame.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from gst.prefetch import background
from gst.registry import sha256_of

log = logging.getLogger("gst.video")

# FFmpeg's and OpenCV's own lines ("[h264 @ 0x...] Invalid NAL unit size", "[ WARN:0@5.6]
# global cap.cpp:212 ...") reached the console above our errors, which say what is wrong with
# which file and frame; quiet unless the user's environment asks for them (read by OpenCV when
# it first opens a video).
if "OPENCV_FFMPEG_LOGLEVEL" not in os.environ:
    os.environ["OPENCV_FFMPEG_LOGLEVEL"] = "-8"  # AV_LOG_QUIET
if "OPENCV_LOG_LEVEL" not in os.environ:
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)

__all__ = [
    "END_SLACK_FRAMES",
    "held_frames",
    "Frame",
    "VideoError",
    "VideoInfo",
    "VideoTruncatedError",
    "check_videos",
    "content_digest",
    "differing_rates",
    "file_identity",
    "frame_range",
    "iter_frames",
    "probe_video",
    "probe_videos",
    "read_frames",
    "scaled_size",
]

# A container's frame count can be an estimate; a shortfall of at most this many frames at the
# very end is taken as the real end rather than as truncation.
END_SLACK_FRAMES = 2


class VideoError(ValueError):
    """A video cannot be read, or does not match the rig or the other cameras."""


class VideoTruncatedError(VideoError):
    """Decoding stopped before the announced end; `frame` is the first frame that failed."""

    def __init__(self, message: str, frame: int):
        super().__init__(message)
        self.frame = frame

    def __reduce__(self):  # rebuilt in the parent when raised in a worker process
        return type(self), (self.args[0], self.frame)


@dataclass(frozen=True)
class VideoInfo:
    """What a video file says about itself (from its container; checked by decoding when
    probed strictly)."""

    path: Path
    width: int
    height: int
    fps: float  # 0 when the container does not say (strict probes only)
    frame_count: int | None  # None when the container does not say
    camera: str = ""

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def frames(self) -> int:
        """Frame count (0 if unknown)."""
        return self.frame_count or 0

    @property
    def duration_s(self) -> float | None:
        return None if self.frame_count is None else self.frame_count / self.fps


@dataclass(frozen=True)
class Frame:
    index: int
    time_s: float
    image: np.ndarray  # (H, W, 3) uint8 BGR


def _who(path: Path, camera: str) -> str:
    return f"camera '{camera}' video {path}" if camera else f"video {path}"


def _open(path: Path, camera: str = "") -> cv2.VideoCapture:
    if path.is_dir():
        raise VideoError(f"{_who(path, camera)}: a folder, not a video file")
    if not path.is_file():
        raise VideoError(f"{_who(path, camera)}: file not found")
    if path.stat().st_size == 0:
        raise VideoError(f"{_who(path, camera)}: the file is empty (0 bytes)")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise VideoError(
            f"{_who(path, camera)}: OpenCV cannot open it (not a video, truncated, an "
            "unsupported codec, or a container that holds no frames)"
        )
    return cap


def still_image_error(path: Path | str) -> str | None:
    """What to tell a user who gave a still image (PNG, JPEG, ... by its content, whatever its
    name) where a video is tracked: FFmpeg opens it as a one-frame video at a made-up 25
    frames/s, and the run ended in "nobody was tracked in 1 frame(s)". None for anything else
    (a raw MJPEG stream starts like a JPEG and is a video)."""
    path = Path(path)
    if path.suffix.lower() in RAW_STREAM_SUFFIXES or not path.is_file():
        return None
    if not cv2.haveImageReader(str(path)):
        return None
    try:  # an animated GIF / WebP / APNG is a video to FFmpeg, and was refused as an image
        if cv2.imcount(str(path)) > 1:
            return None
    except cv2.error:
        pass  # no page count: one image
    return f"{path}: a still image, not a video (expected a video file such as .mp4 or .mov)"


def probe_video(path: Path | str, camera: str = "", *, strict: bool = False) -> VideoInfo:
    """Size, rate and frame count of a video.

    Default: the container's word, and a frame rate is required (times are assigned to frames).
    `strict`: the first frame must decode (its size is used) and the container must report a
    frame count; an unknown rate is allowed (reported as 0). Raises `VideoError` naming the
    camera and file when it is missing, unreadable or empty.
    """
    path = Path(path)
    who = _who(path, camera)
    cap = _open(path, camera)
    try:
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        if strict:
            ok, frame = cap.read()
            if not ok or frame is None:
                raise VideoError(f"{who}: no frame could be decoded (corrupt or empty video)")
            h, w = frame.shape[:2]
    finally:
        cap.release()
    if strict:
        if n <= 0:
            raise VideoError(f"{who}: the container reports {n} frames")
        if not math.isfinite(fps) or fps < 0:
            fps = 0.0
    else:
        if w <= 0 or h <= 0:
            raise VideoError(f"{who}: reports no frame size ({w}x{h}); not a video stream")
        if not math.isfinite(fps) or fps <= 0:
            raise VideoError(
                f"{who}: reports no frame rate (fps = {fps}); cannot assign times to frames"
            )
    if path.suffix.lower() in RAW_STREAM_SUFFIXES and _first_word_on(path):
        log.warning(
            "%s: a raw %s stream holds no frame rate; the decoder's %g frames/s is its default "
            "guess, not the camera's. Put it in a container at its rate (ffmpeg -r 60 -i %s -c "
            "copy out.mp4) or give its rate: scenes.NAME.fps for a scene's cameras, --set "
            "track.fps=60 with --video",
            who, path.suffix.lstrip(".").upper(), fps, path.name,
        )  # fmt: skip
    return VideoInfo(path, w, h, fps, n if n > 0 else None, camera)


_RAW_STREAMS_WARNED: set[Path] = set()


def _first_word_on(path: Path) -> bool:
    """True the first time a raw stream is probed in this process: a run probes each video
    several times (the command line's checks, the stage, the tracker), and the same warning
    was printed three times."""
    key = path.resolve()
    if key in _RAW_STREAMS_WARNED:
        return False
    _RAW_STREAMS_WARNED.add(key)
    return True


# Elementary streams without a container: FFmpeg times them at 25 frames/s whatever they are.
RAW_STREAM_SUFFIXES = (".h264", ".264", ".h265", ".265", ".hevc", ".mjpeg", ".mjpg")


def probe_videos(videos: dict[str, Path], *, strict: bool = False) -> dict[str, VideoInfo]:
    """`probe_video` of every camera's video; one VideoError naming every video that fails
    (only the first was named, so a user fixed and reran once per broken file)."""
    infos, errors = {}, []
    for name, path in videos.items():
        try:
            infos[name] = probe_video(path, name, strict=strict)
        except VideoError as exc:
            errors.append(str(exc))
    if len(errors) == 1:
        raise VideoError(errors[0])
    if errors:
        raise VideoError(f"{len(errors)} videos cannot be read:\n" + "\n".join(errors))
    return infos


FPS_TOLERANCE = 0.01  # relative: 59.94 and 60 frames/s are one rate


def differing_rates(infos: dict[str, VideoInfo]) -> str | None:
    """'c1: 60 (c1.mp4), c2: 50 (c2.mp4)' where the containers' frame rates differ by more than
    FPS_TOLERANCE (a rate of 0, the container not saying, is left out); None where they agree.
    Cameras are paired frame by frame: at different rates frame i is not one instant."""
    rates = {n: i.fps for n, i in infos.items() if i.fps > 0}
    if rates and max(rates.values()) > min(rates.values()) * (1 + FPS_TOLERANCE):
        return ", ".join(f"{n}: {r:g} ({infos[n].path.name})" for n, r in rates.items())
    return None


def check_videos(videos: dict[str, Path], rig_names: Sequence[str]) -> dict[str, VideoInfo]:
    """Probe every camera's video and check them against the rig and against each other.

    Errors name the camera and file: a video whose camera is not in the rig, or frame counts
    that differ across cameras (the cameras must be synchronised frame for frame). Frame sizes
    against the calibration: `calibration.camera.fit_to_frames`.
    """
    if not videos:
        raise VideoError("no videos given: expected a mapping camera name -> video file")
    missing = [name for name in videos if name not in rig_names]
    if missing:
        raise VideoError(
            f"camera(s) {missing} have videos ({', '.join(str(videos[m]) for m in missing)}) "
            f"but are missing from the rig (rig cameras: {list(rig_names)})"
        )
    infos = probe_videos(videos, strict=True)
    # the frames each really holds: a container may announce one or two more than it has (the
    # extraction then failed on the missing last frame and called the file corrupt)
    infos = {n: replace(info, frame_count=held_frames(info)) for n, info in infos.items()}
    counts = {name: info.frames for name, info in infos.items()}
    if len(set(counts.values())) > 1:
        detail = ", ".join(f"{n}: {c} ({infos[n].path.name})" for n, c in counts.items())
        # a 50 frames/s camera among 60 frames/s ones holds fewer frames over the same span: the
        # rates are the cause, and a user who trimmed the videos to one length met them next
        rates = differing_rates(infos)
        also = (
            f"; they also have different frame rates ({rates} frames/s), so frame i is not one "
            "instant in every camera: record or re-encode them at one rate"
            if rates
            else ""
        )
        raise VideoError(
            f"videos have different frame counts across cameras ({detail}); "
            f"expected synchronised videos of equal length{also}"
        )
    return infos


def scaled_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Work-image size for a scale factor. Pixel centres map as u_work = (u + 0.5) * sx - 0.5
    with sx = width_work / width (OpenCV's resize convention)."""
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def read_frames(
    path: Path | str,
    frames: Sequence[int],
    camera: str = "",
    scale: float = 1.0,
    size: tuple[int, int] | None = None,
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, BGR image) for the sorted frame indices in `frames`.

    Decodes sequentially and skips unwanted frames with `grab` (cheaper than seeking in
    compressed video). With `scale` < 1, or a (width, height) `size` other than the frame's
    (which wins over `scale`), the frames are shrunk with area averaging. Raises `VideoError`
    naming the file if the video ends before a requested frame.
    """
    wanted = sorted(set(int(f) for f in frames))
    if not wanted:
        return
    path = Path(path)
    who = _who(path, camera)
    if wanted[0] < 0:  # frame 0 was read and handed out under the negative index
        raise ValueError(f"{who}: frame indices must be >= 0, got {wanted[0]}")
    cap = _open(path, camera)
    try:
        pos = 0
        for f in wanted:
            while pos < f:
                if not cap.grab():
                    raise VideoError(f"{who}: ended at frame {pos}, but frame {f} was requested")
                pos += 1
            ok, image = cap.read()
            if not ok or image is None:
                raise VideoError(
                    f"{who}: frame {f} could not be decoded (truncated or corrupt video: copy "
                    "it again from the camera, or re-encode it)"
                )
            pos += 1
            to = size or (
                scaled_size(image.shape[1], image.shape[0], scale) if scale != 1.0 else None
            )
            if to is not None and tuple(to) != (image.shape[1], image.shape[0]):
                image = cv2.resize(image, tuple(to), interpolation=cv2.INTER_AREA)
            yield f, image
    finally:
        cap.release()


CONTENT_SAMPLE_BYTES = 1 << 20


def content_digest(path: str | Path) -> str:
    """sha256 over a file's size and its first and last MiB: cheap at any length, and different
    for two videos of the same name and byte size (a re-export), which file names, sizes and
    frame counts cannot tell apart. Not a whole-file hash (gst.registry.sha256_of is)."""
    path = Path(path)
    size = path.stat().st_size
    h = hashlib.sha256(str(size).encode())
    with open(path, "rb") as f:
        h.update(f.read(CONTENT_SAMPLE_BYTES))
        if size > CONTENT_SAMPLE_BYTES:
            f.seek(max(CONTENT_SAMPLE_BYTES, size - CONTENT_SAMPLE_BYTES))
            h.update(f.read(CONTENT_SAMPLE_BYTES))
    return h.hexdigest()


def file_identity(path: str | Path, whole: bool = False) -> list:
    """A file by name, size and sampled content (`content_digest`), for cache and resume keys:
    names, not paths, so a moved workspace stays valid; content, not times, so a file copied in
    with its old time (cp -p, rsync -a) is seen, and a copy that only changed the times is not
    taken for another file. `whole`: the whole file's SHA-256 instead, for inputs a user edits
    in place (masks, boxes: a fix in the middle keeps the size and the sampled ends)."""
    path = Path(path)
    digest = sha256_of(path) if whole else content_digest(path)
    return [path.name, path.stat().st_size, digest]


def frame_range(
    info: VideoInfo, start_s: float | None = None, end_s: float | None = None
) -> tuple[int, int | None]:
    """[first, end) frame indices covering times [start_s, end_s); end is None for 'to the end'."""
    for name, value in (("start", start_s), ("end", end_s)):
        # math.ceil raised a bare "cannot convert float NaN/infinity to integer"
        if value is not None and not math.isfinite(value):
            raise ValueError(
                f"{info.path}: time range {name} must be a finite number of seconds or None "
                f"(to the {name} of the video), got {value}"
            )
    eps = 1e-9
    first = 0 if start_s is None else max(0, math.ceil(start_s * info.fps - eps))
    end = None if end_s is None else max(0, math.ceil(end_s * info.fps - eps))
    if info.frame_count is not None:
        end = info.frame_count if end is None else min(end, info.frame_count)
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise ValueError(f"{info.path}: time range end {end_s} s must be after start {start_s} s")
    if info.frame_count is not None and first >= info.frame_count:
        raise VideoError(
            f"{info.path}: start {start_s} s is at or past the end of the video "
            f"({info.frame_count} frames, {info.frame_count / info.fps:.3f} s)"
        )
    if end is not None and first >= end:  # blamed on the video ('no frame could be decoded')
        raise ValueError(
            f"{info.path}: the time range [{start_s or 0} s, {end_s} s) holds no frame at "
            f"{info.fps:g} frames/s (frames {first} to {end - 1})"
        )
    return first, end


def _landed(cap: cv2.VideoCapture, info: VideoInfo, frame: int) -> bool:
    """Seek so that the next read is `frame`, and say whether the landing is confirmed: the
    frame before it is read and must carry its own constant-rate timestamp (frame / fps, within
    a quarter frame). OpenCV seeks by time at the mean rate: MPEG-TS files (camcorders' .MTS)
    land on a keyframe or one frame late, variable-rate files on another frame altogether, and
    the position OpenCV reports back does not show it (docs/formats/tracks_parquet.md)."""
    before = frame - 1
    cap.set(cv2.CAP_PROP_POS_FRAMES, before)
    if int(cap.get(cv2.CAP_PROP_POS_FRAMES)) != before or not cap.grab():
        return False
    ms = cap.get(cv2.CAP_PROP_POS_MSEC)
    return math.isfinite(ms) and abs(ms - before * 1000.0 / info.fps) <= 250.0 / info.fps


def _check_stream_end(info: VideoInfo, index: int) -> None:
    """Decoding stopped at frame `index`: the end of the stream where the container announced
    it (within END_SLACK_FRAMES) or announced nothing; otherwise the file is truncated or
    corrupt, and VideoTruncatedError names the frame."""
    short = None if info.frame_count is None else info.frame_count - index
    if short is None or short <= 0:
        return
    if short <= END_SLACK_FRAMES:  # an estimated count, or the file's last frames lost
        log.warning(
            "%s: decoding ended at frame %d, %d before the %d frames the container announces; "
            "taken as the end of the video", info.path, index, short, info.frame_count,
        )  # fmt: skip
        return
    raise VideoTruncatedError(
        f"{info.path}: decoding failed at frame {index} of {info.frame_count} announced (file "
        f"truncated or corrupt: copy it again from the camera, or re-encode it); frames before "
        f"{index} decoded fine",
        index,
    )


class _RateCheck:
    """Frame times are frame / fps, the container's mean rate: right for a constant-rate file,
    wrong for a variable-rate one (phones record so), where speeds from them come out wrong by
    the ratio of the rates, and the run said nothing. Each decoded frame's own timestamp is
    compared with its constant-rate time (from the first frame's, so a stream that starts at an
    offset is not taken for one); past half a frame the file is named, once."""

    def __init__(self, info: VideoInfo):
        self.info, self.origin, self.warned = info, None, False

    def check(self, cap: cv2.VideoCapture, index: int) -> None:
        if self.warned or not self.info.fps > 0:
            return
        ms = cap.get(cv2.CAP_PROP_POS_MSEC)
        if not math.isfinite(ms):
            return
        steady = index * 1000.0 / self.info.fps
        if self.origin is None:
            self.origin = ms - steady
            return
        if abs(ms - self.origin - steady) > 500.0 / self.info.fps:
            self.warned = True
            log.warning(
                "%s: variable frame rate: frame %d is stamped %.3f s into the video, but times "
                "here are frame / %g frames/s (the mean rate) = %.3f s; time_s, speeds and "
                "start_s/end_s are off by as much. Re-encode it at a constant rate first (e.g. "
                "ffmpeg -i IN -vsync cfr -r 60 OUT.mp4)",
                self.info.path, index, (ms - self.origin) / 1000.0, self.info.fps,
                steady / 1000.0,
            )  # fmt: skip


def _decode(
    info: VideoInfo, first: int, end: int | None, stride: int, rate: float
) -> Iterator[Frame]:
    """Frames first, first + stride, ... before `end`, timed at `rate` (seeking and the rate
    check on the container's own timestamps, `info`)."""
    if end is not None and first >= end:
        return
    cap = _open(info.path, info.camera)
    try:
        if first > 0 and not _landed(cap, info, first):
            # not frame-exact here: every frame up to `first` is grabbed from the start instead
            log.warning(
                "%s: seeking is not frame-exact in this file (a transport stream or a variable "
                "frame rate); reading %d frames from the start to reach frame %d",
                info.path, first, first,
            )  # fmt: skip
            cap.release()
            cap = _open(info.path, info.camera)
            for k in range(first):
                if not cap.grab():
                    _check_stream_end(info, k)  # the stream ends before `first`: no frames
                    return
        index = first
        clock = _RateCheck(info)
        while end is None or index < end:
            ok, image = cap.read()
            if not ok or image is None:
                _check_stream_end(info, index)
                return
            clock.check(cap, index)
            yield Frame(index, index / rate, image)
            index += 1
            for _ in range(stride - 1):
                if end is not None and index >= end:
                    break
                if not cap.grab():  # a skipped frame is checked like a read one
                    _check_stream_end(info, index)
                    return
                index += 1
        if end is not None and end == info.frame_count and cap.grab():
            # the container announced fewer frames than it holds (a count estimated from the
            # duration, or a header written before the recording ended): the rest is not read
            log.warning(
                "%s: the container announces %d frames but holds more; frames from %d on are "
                "not read (re-mux the file to fix its header, e.g. ffmpeg -i IN -c copy OUT)",
                info.path, info.frame_count, info.frame_count,
            )  # fmt: skip
    finally:
        cap.release()


def held_frames(info: VideoInfo) -> int:
    """The frames the video really holds: the count its container announces, less the frames
    missing at its end where there are at most END_SLACK_FRAMES of them (the tracking reader
    takes such a file's last decodable frame as its end; a reader that trusted the count
    failed on the missing frame, calling the file corrupt). Seeks to the last few frames and
    grabs them; where seeking is not frame-exact (a transport stream, a variable or unknown
    rate) the announced count is kept rather than decoding the whole file to check it."""
    n = info.frame_count
    if n is None or n <= END_SLACK_FRAMES + 1 or not info.fps > 0:
        return info.frames
    start = n - END_SLACK_FRAMES - 1
    cap = _open(info.path, info.camera)
    try:
        if not _landed(cap, info, start):
            return n
        held = start
        while held < n and cap.grab():
            held += 1
    finally:
        cap.release()
    _check_stream_end(info, held)  # a missing end said, more than the slack refused
    return held


def iter_frames(
    path: str | Path,
    *,
    stride: int = 1,
    start_s: float | None = None,
    end_s: float | None = None,
    start_frame: int | None = None,
    end_frame: int | None = None,
    prefetch: int = 0,
    fps: float | None = None,
) -> Iterator[Frame]:
    """Yield frames first, first + stride, ... within [start_s, end_s).

    `start_frame` (used to resume, or to start a chunk) overrides the first frame; it must lie on
    the stride grid. `end_frame` (exclusive) stops earlier than `end_s` (a chunk's end).
    `prefetch` > 0 decodes that many frames ahead in a thread. `fps`: the rate to time the
    frames at where the header's is not to be trusted (frame times and the [start_s, end_s)
    range follow it; seeking still uses the container's own timestamps).
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if fps is not None and not (math.isfinite(fps) and fps > 0):  # 0 failed at the first frame
        raise ValueError(f"{path}: fps must be > 0 frames/s, got {fps}")
    info = probe_video(path)
    timing = info if fps is None else replace(info, fps=float(fps))
    first, end = frame_range(timing, start_s, end_s)
    if start_frame is not None:
        if start_frame < first or (start_frame - first) % stride:
            raise ValueError(
                f"{path}: start_frame {start_frame} is not on the grid {first} + k * {stride}"
            )
        first = start_frame
    if end_frame is not None:
        end = end_frame if end is None else min(end, end_frame)
    frames = _decode(info, first, end, stride, rate=timing.fps)
    return background(frames, prefetch, name="video-decode") if prefetch > 0 else frames
