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

import importlib
import importlib.metadata
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gst.atomic import atomic_save_npz
from gst.detect.weights import MODELS
from gst.registry import sha256_of
from gst.track.detection import N_LANDMARKS, Detection, Detector
from gst.track.writer import settings_digest

__all__ = [
    "DETECTOR_MODULES",
    "KeptDetections",
    "RecordingDetector",
    "detections_key",
    "load_detections",
]

log = logging.getLogger("gst.track")

FORMAT = 1
# the modules whose code decides what the learned person model finds
# (gst.detect.weights pins the model files by their SHA-256)
DETECTOR_MODULES = (
    "gst.video",
    "gst.detect.blazepose",
    "gst.detect.boxes",
    "gst.detect.persons",
    "gst.detect.weights",
    "gst.track.detection",
    "gst.track.person_detector",
)
# the libraries that run them (OpenCV by its module's own version: any wheel may provide cv2)
DETECTOR_PACKAGES = ("ai-edge-litert", "numpy")


def _code() -> dict[str, str]:
    """The SHA-256 of each detector module's source and the libraries' versions."""
    out = {
        name: sha256_of(Path(importlib.import_module(name).__file__)) for name in DETECTOR_MODULES
    }
    for package in DETECTOR_PACKAGES:
        try:
            out[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            out[package] = "not installed"
    out["opencv"] = cv2.__version__
    return out


def detections_key(video: str | Path, detector_info: dict, first_frame: int, stride: int) -> str:
    """The file name (without folder) of the video's detections for this detector and run."""
    what = {
        "format": FORMAT,
        "video": sha256_of(Path(video)),
        "detector": detector_info,
        # the models' pins: model_paths refuses any other file, so they name the models run
        "models": {role: m.sha256 for role, m in MODELS.items()},
        "code": _code(),
        "first_frame": int(first_frame),
        "stride": int(stride),
    }
    return f"detections-{settings_digest(what)[:32]}.npz"


@dataclass(frozen=True)
class KeptDetections:
    """The detections of a run's frames, as arrays (`RecordingDetector.save` writes them):
    frame f's are rows starts[f] .. starts[f] + counts[f] of the per-detection arrays. A
    detector that replays them (`detect`)."""

    starts: dict[int, tuple[int, int]]  # frame -> (first row, number of rows)
    boxes: np.ndarray  # (N, 4) float64
    scores: np.ndarray  # (N,) float64
    landmarks: np.ndarray  # (N, 33, 3) float32, NaN where has_landmarks is false
    has_landmarks: np.ndarray  # (N,) bool

    def detect(self, frame_bgr: np.ndarray | None, frame_index: int) -> list[Detection]:
        if frame_index not in self.starts:
            raise ValueError(f"no kept detections for frame {frame_index}")
        a, n = self.starts[frame_index]
        return [
            Detection(
                self.boxes[i],
                float(self.scores[i]),
                landmarks=self.landmarks[i] if self.has_landmarks[i] else None,
            )
            for i in range(a, a + n)
        ]


def load_detections(
    path: Path, first_frame: int, stride: int, end_frame: int
) -> KeptDetections | None:
    """The detections of frames first_frame, first_frame + stride, ... < end_frame from the file,
    or None where it is missing, unreadable or does not reach that far. A file written by a run
    planned to reach at least `end_frame` whose decoding stopped earlier (a container that
    counts a frame or two more than it holds) serves the frames it has: the same bytes stop at
    the same frame."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != FORMAT or int(z["end_frame"]) < end_frame:
                return None
            frames, counts = z["frames"], z["counts"]
            kept = KeptDetections(
                {},
                z["boxes"],
                z["scores"],
                z["landmarks"],
                z["has_landmarks"],
            )
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("%s: not read (%s); the person model runs again", path, exc)
        return None
    last = int(frames[-1]) if len(frames) else first_frame - 1
    wanted = set(range(first_frame, min(end_frame, last + 1), stride))
    starts = np.r_[0, np.cumsum(counts)].tolist()
    for k, f in enumerate(frames.tolist()):
        if f in wanted:
            kept.starts[f] = (starts[k], starts[k + 1] - starts[k])
    if set(kept.starts) != wanted or not wanted:
        log.warning("%s: does not hold the run's frames; the person model runs again", path)
        return None
    return kept


class RecordingDetector:
    """A detector as given that also keeps what it found, frame by frame, as arrays (a long
    video's detections as objects would take several times the memory), to `save` them."""

    def __init__(self, inner: Detector):
        self.inner = inner
        self._frames: list[int] = []
        self._counts: list[int] = []
        self._boxes: list[np.ndarray] = []
        self._scores: list[np.ndarray] = []
        self._landmarks: list[np.ndarray] = []
        self._has: list[np.ndarray] = []

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        found = self.inner.detect(frame_bgr, frame_index)
        self._frames.append(int(frame_index))
        self._counts.append(len(found))
        if found:
            lms = np.full((len(found), N_LANDMARKS, 3), np.nan, np.float32)
            for i, d in enumerate(found):
                if d.landmarks is not None:
                    lms[i] = d.landmarks
            self._boxes.append(np.array([d.box for d in found], np.float64))
            self._scores.append(np.array([d.score for d in found], np.float64))
            self._landmarks.append(lms)
            self._has.append(np.array([d.landmarks is not None for d in found], bool))
        return found

    def save(self, path: Path, end_frame: int) -> None:
        """Write the kept detections, valid for runs planned to end at or before `end_frame`."""

        def joined(parts: list[np.ndarray], shape: tuple, dtype) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros((0, *shape), dtype)

        atomic_save_npz(
            path,
            format=np.int64(FORMAT),
            end_frame=np.int64(end_frame),
            frames=np.asarray(self._frames, np.int64),
            counts=np.asarray(self._counts, np.int64),
            boxes=joined(self._boxes, (4,), np.float64),
            scores=joined(self._scores, (), np.float64),
            landmarks=joined(self._landmarks, (N_LANDMARKS, 3), np.float32),
            has_landmarks=joined(self._has, (), bool),
        )
