"""Per-frame work before the network: cut each detection's crop and describe its appearance,
and the per-group bookkeeping of tracking (tracker, smoother, counters) after it."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from gst.data.camera_view import TrackingView
from gst.data.crop import crop_intrinsics, crop_window
from gst.track.appearance import box_histogram
from gst.track.detection import N_LANDMARKS, Detection
from gst.track.predictor import PoseBatch
from gst.track.rows import RowSet
from gst.track.smoothing import OneEuroConfig, PoseSmoother
from gst.track.tracker import Observation, Tracker, TrackerConfig

# the session's counters (`TrackingSession.stats`, written to gst.stats; summed over chunks)
STAT_KEYS = (
    "frames",
    "rows",
    "detections",
    "dropped_nonfinite",
    "dropped_low_score",
    "dropped_parts",
    "landmarks_exchanged",  # detections whose left/right labels gst.track.mirror exchanged
)


@dataclass
class PendingFrame:
    """One processed frame's detections while its group is being assembled."""

    index: int
    time_s: float
    boxes: np.ndarray  # (n, 4) raw-frame boxes
    scores: np.ndarray  # (n,)
    appearance: np.ndarray  # (n, D)
    landmarks: np.ndarray  # (n, 33, 3) u, v, confidence; NaN where the detector gave none


@dataclass
class PreparedDetection:
    """One detection cut out for the network."""

    crop_rgb: np.ndarray  # (S, S, 3) uint8
    K_crop: np.ndarray  # (3, 3)
    appearance: np.ndarray  # (D,) colour histogram
    landmarks_crop: np.ndarray  # (33, 3) u, v in crop pixels + confidence; NaN when unknown


def _landmarks_in_crop(view: TrackingView, window, landmarks: np.ndarray | None) -> np.ndarray:
    if landmarks is None:
        return np.full((N_LANDMARKS, 3), np.nan, np.float32)
    uv = landmarks[:, :2].astype(np.float64)
    if view.has_distortion:  # crops are cut from the undistorted image
        # exact_only: a landmark placed outside the frame beyond where the lens model inverts
        # came back hundreds of pixels off; unknown (NaN) instead
        xy = view.camera.undistort_points(uv, exact_only=True)
        uv = xy @ view.camera.K[:2, :2].T + view.camera.K[:2, 2]
    return np.c_[window.to_crop(uv), landmarks[:, 2]].astype(np.float32)


@functools.lru_cache(maxsize=4)
def _blank(size: int) -> np.ndarray:
    blank = np.zeros((size, size, 3), np.uint8)
    blank.flags.writeable = False
    return blank


def is_blank(crop_rgb: np.ndarray) -> bool:
    """Whether `crop_rgb` is the shared blank that stands for a crop not cut (`pixels` False):
    callers may skip reading its pixels (identity, not content: a cut crop that happens to be
    black is not blank)."""
    return crop_rgb.ndim == 3 and crop_rgb is _blank(crop_rgb.shape[0])


def prepare_detection(
    view: TrackingView, frame_bgr: np.ndarray, det: Detection, size: int, pixels: bool = True
) -> PreparedDetection:
    """Crop, K_crop, appearance histogram and crop-space landmarks of one detection.

    `pixels` False: the network will not read this crop (its pose comes from the landmarks,
    `GSTPredictor.needs_pixels`), so no crop is cut and `crop_rgb` is blank. The histogram is
    read from the frame itself either way (`box_histogram`), so that every detection of a video
    is described alike."""
    box = view.model_box(det.box)  # in the undistorted image when the lens distorts
    window = crop_window(box, size)
    K_crop = crop_intrinsics(view.camera.K, window)
    if det.mask is not None and np.shape(det.mask) != frame_bgr.shape[:2]:
        raise ValueError(
            f"detection mask has shape {np.shape(det.mask)}, expected the frame's "
            f"{frame_bgr.shape[:2]}"
        )
    hist = box_histogram(frame_bgr, det.box, det.mask)
    if pixels:
        crop_bgr, _ = view.crop(frame_bgr, window)
        crop_rgb = cv2.cvtColor(crop_bgr, cv2.COLOR_BGR2RGB)
    else:
        crop_rgb = _blank(size)
    return PreparedDetection(
        crop_rgb, K_crop, hist, _landmarks_in_crop(view, window, det.landmarks)
    )


_POSE_KEYS = ("rotmats", "betas", "transl_cam", "joints_cam")


def _row_json(row: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in row.items()}


def _row_from_json(d: dict) -> dict:
    out = dict(d)
    for k in ("box", "landmarks", *_POSE_KEYS):
        if out.get(k) is not None:
            out[k] = np.asarray(out[k], np.float32 if k == "landmarks" else np.float64)
    out["key"] = tuple(out["key"])
    return out


class TrackingSession:
    """Tracker, smoother, counters and the rows of tentative people: everything a resumed run
    must restore.

    A detection of a tentative track has no id yet; its row is held (`pending`, saved with the
    state) until the track is confirmed, then written with the id (before the confirming
    frame's row, so the smoother sees the person's frames in order), or dropped with the track.
    """

    def __init__(self, tracker: TrackerConfig, smoothing: OneEuroConfig | None):
        self.tracker = Tracker(tracker)
        self.smoother = PoseSmoother(smoothing) if smoothing else None
        self.pending: dict[tuple, dict] = {}
        self.stats = dict.fromkeys(STAT_KEYS, 0)

    def state_dict(self) -> dict:
        return {
            "tracker": self.tracker.state_dict(),
            "smoother": self.smoother.state_dict() if self.smoother else {},
            "stats": dict(self.stats),
            "pending": [_row_json(r) for r in self.pending.values()],
        }

    def load_state_dict(self, state: dict) -> None:
        self.tracker.load_state_dict(state["tracker"])
        if self.smoother:
            self.smoother.load_state_dict(state["smoother"])
        self.stats = {**self.stats, **state["stats"]}
        rows = [_row_from_json(d) for d in state.get("pending", [])]
        self.pending = {r["key"]: r for r in rows}

    def _emit(self, rows: list[dict], row: dict, pid: int) -> None:
        if self.smoother:
            s = self.smoother(pid, row["time_s"], {q: row[q] for q in _POSE_KEYS})
            row = {**row, **s}
        rows.append({**row, "person_id": pid})

    def track_group(
        self, view: TrackingView, group: list[PendingFrame], poses: PoseBatch
    ) -> RowSet:
        """The rows this group's detections make final: those that got an id now, and the held
        rows of people confirmed in this group (possibly from earlier frames)."""
        finite = poses.finite()
        rows: list[dict] = []
        k = 0
        for f in group:
            n = len(f.scores)
            idx = np.arange(k, k + n)[finite[k : k + n]]
            self.stats["dropped_nonfinite"] += int(n - len(idx))
            pelvis = poses.joints_cam[idx, 0]
            pos = view.to_world(pelvis) if view.calibrated else pelvis
            obs = [
                Observation(
                    f.boxes[j - k],
                    pos[i],
                    f.appearance[j - k],
                    float(f.scores[j - k]),
                    key=(f.index, int(j - k)),
                    landmarks=_landmarks_or_none(f.landmarks[j - k]),
                )
                for i, j in enumerate(idx)
            ]
            got = self.tracker.step(f.time_s, obs)
            for key, pid in got.backfill:
                self._emit(rows, self.pending.pop(key), pid)
            for i, (j, pid) in enumerate(zip(idx, got.ids, strict=True)):
                row = {
                    "key": obs[i].key,
                    "frame": f.index,
                    "time_s": f.time_s,
                    "box": f.boxes[j - k],
                    "score": float(f.scores[j - k]),
                    "landmarks": f.landmarks[j - k],
                    "source": int(j),
                    **{q: getattr(poses, q)[j] for q in _POSE_KEYS},
                }
                if pid >= 0:
                    self._emit(rows, row, pid)
                elif i in got.parts:
                    self.stats["dropped_parts"] += 1
                else:
                    row["source"] = -1  # extras are not held
                    self.pending[obs[i].key] = row
            live = self.tracker.pending_keys()
            for key in [key for key in self.pending if key not in live]:
                del self.pending[key]  # a tentative track that ended: its detections never count
                self.stats["dropped_low_score"] += 1
            if self.smoother:
                self.smoother.retain({t.id for t in self.tracker.tracks})
            k += n
        self.stats["frames"] += len(group)
        self.stats["detections"] += len(poses)
        self.stats["rows"] += len(rows)
        return RowSet.from_rows(rows, poses.betas.shape[1])


def _landmarks_or_none(lm: np.ndarray) -> np.ndarray | None:
    return None if not np.isfinite(lm).all() else lm
