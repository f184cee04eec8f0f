"""`PersonModelDetector`: people from the learned BlazePose segmenter (gst.detect), for footage
where the background model fails (people who stand still, cameras that move, no empty plate).

It runs at a work resolution (longer side `max_side` px), keeps its own tracking state across
frames (the previous frame's landmarks seed the next frame's regions), and returns each
person's mask box at full resolution with the landmark model's presence as the score. Frames
must come in order; a frame index that goes back (or repeats) resets the state, and a forward
jump of more than `max_gap` frames does too.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gst.detect.blazepose import BlazePose
from gst.detect.persons import PersonSegmenter, SegmenterConfig
from gst.metrics.image import box_iou
from gst.track.detection import Detection


class PersonModelDetector:
    def __init__(
        self,
        *,
        models_dir: str | Path | None = None,
        max_side: int = 960,
        config: SegmenterConfig | None = None,
        min_height_frac: float = 0.08,
        threads: int = 1,
        duplicate_iou: float = 0.6,
        max_gap: int = 5,
    ):
        self.segmenter = PersonSegmenter(
            BlazePose(models_dir, threads=threads), config or SegmenterConfig()
        )
        self.max_side = max_side
        self.min_height_frac = min_height_frac
        self.duplicate_iou = duplicate_iou
        self.max_gap = max_gap  # frames; a stride up to this keeps the tracked regions
        self._last: int | None = None

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        if self._last is not None and not 0 < frame_index - self._last <= self.max_gap:
            self.segmenter.reset()
        self._last = frame_index
        h, w = frame_bgr.shape[:2]
        s = min(1.0, self.max_side / max(h, w))
        small = (
            frame_bgr
            if s == 1.0
            else cv2.resize(frame_bgr, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        )
        labels, people = self.segmenter.segment(small)
        out = []
        for k, person in enumerate(people, start=1):
            ys, xs = np.nonzero(labels == k)
            if len(xs) == 0:
                continue
            box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64) / s
            if box[3] - box[1] < self.min_height_frac * h:
                continue
            # One person found twice (a partial second region) overlaps its own box heavily.
            if any(float(box_iou(box[None], d.box[None])[0, 0]) > self.duplicate_iou for d in out):
                continue
            out.append(Detection(box=box, score=float(person.presence)))
        return out
