"""Per-frame work before the network: cut each detection's crop and describe its appearance,
and the per-group bookkeeping of tracking (tracker, smoother, counters) after it."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gst.data.camera_view import TrackingView
from gst.data.crop import crop_window, cut_crop, cut_undistorted_crop
from gst.track.appearance import colour_histogram, core_region
from gst.track.detection import Detection
from gst.track.predictor import PoseBatch
from gst.track.smoothing import OneEuroConfig, PoseSmoother
from gst.track.tracker import Observation, Tracker, TrackerConfig


@dataclass
class PendingFrame:
    """One processed frame's detections while its group is being assembled."""

    index: int
    time_s: float
    boxes: np.ndarray  # (n, 4) raw-frame boxes
    scores: np.ndarray  # (n,)
    appearance: np.ndarray  # (n, D)


def prepare_detection(
    view: TrackingView, frame_bgr: np.ndarray, det: Detection, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(RGB crop, K_crop, appearance histogram) of one detection."""
    box = view.model_box(det.box)  # in the undistorted image when the lens distorts
    window = crop_window(box, size)
    crop_bgr, K_crop = view.crop(frame_bgr, window)
    crop_rgb = cv2.cvtColor(crop_bgr, cv2.COLOR_BGR2RGB)
    box_in_crop = (box - [window.x0, window.y0, window.x0, window.y0]) * window.scale
    if det.mask is not None:
        m = np.asarray(det.mask, dtype=np.uint8)
        if m.shape != frame_bgr.shape[:2]:
            raise ValueError(
                f"detection mask has shape {m.shape}, expected the frame's {frame_bgr.shape[:2]}"
            )
        mc = (
            cut_undistorted_crop(m, view.camera, window, cv2.INTER_NEAREST)
            if view.has_distortion
            else cut_crop(m, window, cv2.INTER_NEAREST)
        )
        rows, cols = core_region(size, box_in_crop, 0.0, 0.0)
        hist = colour_histogram(crop_rgb[rows, cols], (mc[rows, cols] > 0).astype(np.uint8))
    else:
        rows, cols = core_region(size, box_in_crop)
        hist = colour_histogram(crop_rgb[rows, cols])
    return crop_rgb, K_crop, hist


class TrackingSession:
    """Tracker, smoother and counters: everything a resumed run must restore."""

    def __init__(self, tracker: TrackerConfig, smoothing: OneEuroConfig | None):
        self.tracker = Tracker(tracker)
        self.smoother = PoseSmoother(smoothing) if smoothing else None
        self.stats = {
            "frames": 0,
            "rows": 0,
            "detections": 0,
            "dropped_nonfinite": 0,
            "dropped_low_score": 0,
        }

    def state_dict(self) -> dict:
        return {
            "tracker": self.tracker.state_dict(),
            "smoother": self.smoother.state_dict() if self.smoother else {},
            "stats": dict(self.stats),
        }

    def load_state_dict(self, state: dict) -> None:
        self.tracker.load_state_dict(state["tracker"])
        if self.smoother:
            self.smoother.load_state_dict(state["smoother"])
        self.stats = dict(state["stats"])

    def track_group(
        self, view: TrackingView, group: list[PendingFrame], poses: PoseBatch
    ) -> tuple[list[list[int]], PoseBatch, np.ndarray]:
        """Ids for every detection (-1: none), smoothed poses, and which detections to keep."""
        finite = poses.finite()
        ids: list[list[int]] = []
        keep = np.zeros(len(poses), bool)
        out = PoseBatch(
            poses.rotmats.copy(),
            poses.betas.copy(),
            poses.transl_cam.copy(),
            poses.joints_cam.copy(),
            {},
        )
        k = 0
        for f in group:
            n = len(f.scores)
            idx = np.arange(k, k + n)[finite[k : k + n]]
            self.stats["dropped_nonfinite"] += int(n - len(idx))
            pelvis = out.joints_cam[idx, 0]
            pos = view.to_world(pelvis) if view.calibrated else pelvis
            obs = [
                Observation(f.boxes[j - k], pos[i], f.appearance[j - k], float(f.scores[j - k]))
                for i, j in enumerate(idx)
            ]
            got = self.tracker.update(f.time_s, obs)
            frame_ids = [-1] * n
            for j, pid in zip(idx, got, strict=True):
                frame_ids[j - k] = pid
                if pid >= 0:
                    keep[j] = True
                    if self.smoother:
                        s = self.smoother(
                            pid,
                            f.time_s,
                            {
                                q: getattr(out, q)[j]
                                for q in ("rotmats", "betas", "transl_cam", "joints_cam")
                            },
                        )
                        for q, v in s.items():
                            getattr(out, q)[j] = v
                else:
                    self.stats["dropped_low_score"] += 1
            if self.smoother:
                self.smoother.retain({t.id for t in self.tracker.tracks})
            ids.append(frame_ids)
            k += n
        self.stats["frames"] += len(group)
        self.stats["detections"] += len(poses)
        self.stats["rows"] += int(keep.sum())
        return ids, out, keep
