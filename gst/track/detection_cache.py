"""The person model's detections of a video, kept for the next `track` run over it.

Most of `track`'s time on real footage is the learned person model (gst.track.person_detector).
What it finds depends only on the video's pixels, the model files, the person model's code and
settings, and which frames are processed (first frame and stride: it tracks from frame to
frame). Tracking the same video again, after a new network was trained or with other tracker
settings, finds the same people, so the first run writes them to a file and later runs replay
it instead of running the model.

The file's name is a digest of all that decides the detections (`detections_key`): the
video's bytes, the detector's description (name, model, settings), the source of the modules
that compute them and pin the model files (`DETECTOR_MODULES`), the versions of the libraries
that run them (`DETECTOR_PACKAGES`), the file format, the first frame and the stride. A run
replays a file whose frames reach at least as far as its own (a shorter run replays the start
of a longer one: a frame's detections depend only on the frames before it); otherwise it runs
the model and writes the file once its last frame is done, atomically
(docs/formats/detections_npz.md). A file that cannot be read, or that holds other frames, is
not used: the model runs and the file is written again.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import json
import logging
import zipfile
from pathlib import Path

import numpy as np

from gst.atomic import atomic_path
from gst.track.detection import N_LANDMARKS, Detection, Detector

__all__ = [
    "DETECTOR_MODULES",
    "RecordingDetector",
    "ReplayedDetector",
    "detections_key",
    "load_detections",
    "video_digest",
]

log = logging.getLogger("gst.track")

FORMAT = 1
# the modules whose code decides what the learned person model finds
# (gst.detect.weights pins the model files by their SHA-256)
DETECTOR_MODULES = (
    "gst.detect.blazepose",
    "gst.detect.boxes",
    "gst.detect.persons",
    "gst.detect.weights",
    "gst.track.detection",
    "gst.track.person_detector",
)
# the libraries that run them
DETECTOR_PACKAGES = ("ai-edge-litert", "opencv-contrib-python-headless", "numpy")
_CHUNK = 8 << 20


def video_digest(path: str | Path) -> str:
    """BLAKE2b of the video file's bytes (hex, 32 characters)."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while block := f.read(_CHUNK):
            h.update(block)
    return h.hexdigest()


def _code_digest() -> str:
    h = hashlib.blake2b(digest_size=16)
    for name in DETECTOR_MODULES:
        h.update(name.encode())
        h.update(Path(importlib.import_module(name).__file__).read_bytes())
    for package in DETECTOR_PACKAGES:
        try:
            version = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            version = "not installed"
        h.update(f"{package}=={version}".encode())
    return h.hexdigest()


def detections_key(video: str | Path, detector_info: dict, first_frame: int, stride: int) -> str:
    """The file name (without folder) of the video's detections for this detector and run."""
    what = {
        "format": FORMAT,
        "video": video_digest(video),
        "detector": detector_info,
        "code": _code_digest(),
        "first_frame": int(first_frame),
        "stride": int(stride),
    }
    digest = hashlib.blake2b(json.dumps(what, sort_keys=True).encode(), digest_size=16)
    return f"detections-{digest.hexdigest()}.npz"


def load_detections(
    path: Path, first_frame: int, stride: int, end_frame: int
) -> dict[int, list[Detection]] | None:
    """The detections of frames first_frame, first_frame + stride, ... < end_frame from the file,
    or None where it is missing, unreadable or does not reach that far."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != FORMAT or int(z["end_frame"]) < end_frame:
                return None
            frames, counts = z["frames"], z["counts"]
            boxes, scores, landmarks = z["boxes"], z["scores"], z["landmarks"]
            has = z["has_landmarks"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("%s: not read (%s); the person model runs again", path, exc)
        return None
    wanted = set(range(first_frame, end_frame, stride))
    starts = np.r_[0, np.cumsum(counts)]
    out: dict[int, list[Detection]] = {}
    for f, a, b in zip(frames.tolist(), starts[:-1], starts[1:], strict=True):
        if f in wanted:
            out[f] = [
                Detection(boxes[i], float(scores[i]), landmarks=landmarks[i] if has[i] else None)
                for i in range(a, b)
            ]
    if set(out) != wanted:
        log.warning("%s: does not hold the run's frames; the person model runs again", path)
        return None
    return out


class ReplayedDetector:
    """A detector that gives the detections read from a file (`load_detections`)."""

    def __init__(self, detections: dict[int, list[Detection]]):
        self._detections = detections

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        try:
            return self._detections[frame_index]
        except KeyError:
            raise ValueError(f"no kept detections for frame {frame_index}") from None


class RecordingDetector:
    """A detector as given that also keeps what it found, frame by frame, to `save` them."""

    def __init__(self, inner: Detector):
        self.inner = inner
        self._frames: list[int] = []
        self._found: list[list[Detection]] = []

    def __getattr__(self, name: str):  # counters and settings of the detector (benchmarks)
        if name == "inner":  # not set yet (a copy being made): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        found = self.inner.detect(frame_bgr, frame_index)
        self._frames.append(int(frame_index))
        self._found.append(list(found))
        return found

    def save(self, path: Path, end_frame: int) -> None:
        """Write the kept detections, valid for runs that end at or before `end_frame`."""
        flat = [d for ds in self._found for d in ds]
        lms = np.full((len(flat), N_LANDMARKS, 3), np.nan, np.float32)
        for i, d in enumerate(flat):
            if d.landmarks is not None:
                lms[i] = d.landmarks
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                format=np.int64(FORMAT),
                end_frame=np.int64(end_frame),
                frames=np.asarray(self._frames, np.int64),
                counts=np.asarray([len(ds) for ds in self._found], np.int64),
                boxes=np.asarray([d.box for d in flat], np.float64).reshape(-1, 4),
                scores=np.asarray([d.score for d in flat], np.float64),
                landmarks=lms,
                has_landmarks=np.asarray([d.landmarks is not None for d in flat], bool),
            )
