"""A person detector for static cameras, built on the extraction library's background model.

The background is learnt once per video from frames sampled across it (or from a clip of the
empty scene, which is what makes people who barely move visible); each frame's foreground is
cleaned (morphology, hole filling, component filters) and every remaining blob is a person box.
Masks are computed at reduced resolution (`work_scale`) for speed; boxes are returned in full
frame pixels (corner convention).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gst.data.background import BackgroundConfig, build_background, sample_indices
from gst.data.masks import MaskConfig, clean_mask
from gst.data.video import probe_video, read_frames
from gst.track.detection import Detection


class StaticCameraDetector:
    """`detect(frame_bgr, frame_index) -> [Detection]` from a learnt background."""

    def __init__(self, video: str | Path, *, plate: str | Path | None = None, work_scale: float = 0.5,
                 background: BackgroundConfig | None = None, masks: MaskConfig | None = None,
                 min_height_frac: float = 0.08):
        self.config = background or BackgroundConfig()
        self.mask_config = masks or MaskConfig()
        self.work_scale = float(work_scale)
        self.min_height_frac = min_height_frac
        source = Path(plate) if plate is not None else Path(video)
        info = probe_video(source, source.stem)
        picks = sample_indices(info.frames, min(self.config.samples, info.frames))
        samples = np.stack([img for _, img in read_frames(source, picks, source.stem, scale=self.work_scale)])
        self.model = build_background(samples, self.config)
        self.work_size = samples.shape[2], samples.shape[1]

    def detect(self, frame_bgr: np.ndarray, frame_index: int) -> list[Detection]:
        h, w = frame_bgr.shape[:2]
        small = cv2.resize(frame_bgr, self.work_size, interpolation=cv2.INTER_AREA)
        labels, blobs = clean_mask(self.model.foreground(small), self.mask_config)
        sx, sy = w / self.work_size[0], h / self.work_size[1]
        out = []
        for b in blobs:
            x, y, bw, bh = b.box
            if bh * sy < self.min_height_frac * h:
                continue
            box = np.array([x * sx, y * sy, (x + bw) * sx, (y + bh) * sy])
            out.append(Detection(box=box, score=float(min(1.0, b.area / max(1, bw * bh) + 0.5))))
        return out
