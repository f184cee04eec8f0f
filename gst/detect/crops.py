"""BlazePose's landmarks on crops that already frame one person (the extraction's, training's
and tracking's square crops): the whole crop is the landmark model's region of interest.

The one place the crop pipelines run the landmark model; training, fusion and the lifting
dataset call it, and read the store's `landmarks` instead when the extraction wrote them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gst.detect.blazepose import N_BODY_LANDMARKS, BlazePose, BodyRoi


@dataclass(frozen=True)
class CropLandmarks:
    """BlazePose on N crops: crop-pixel landmarks with visibility, world landmarks (metres,
    mid-hip origin, the crop camera's axes; `PersonSegment.world_landmarks`) and presence."""

    landmarks: np.ndarray  # (N, 33, 3) u, v in crop pixels, visibility in [0, 1]
    world: np.ndarray  # (N, 33, 3)
    presence: np.ndarray  # (N,)

    def __len__(self) -> int:
        return len(self.presence)

    def with_confidence(self) -> np.ndarray:
        """(N, 33, 3) u, v and confidence = visibility x presence (the store's layout)."""
        out = self.landmarks.copy()
        out[..., 2] *= self.presence[:, None]
        return out


def detect_crop_landmarks(
    images: np.ndarray, model: BlazePose | None = None, *, rgb: bool, progress=None
) -> CropLandmarks:
    """The landmark model on (N, S, S, 3) uint8 crops (`rgb` says the channel order: CropSet
    images are RGB, store and video frames BGR), each crop as one upright region."""
    images = np.asarray(images)
    n, size = len(images), (images.shape[1] if len(images) else 0)
    model = model or BlazePose(threads=1)
    roi = BodyRoi(((size - 1) / 2, (size - 1) / 2), float(size), 0.0)
    lms = np.zeros((n, N_BODY_LANDMARKS, 3), np.float32)
    world = np.zeros((n, N_BODY_LANDMARKS, 3), np.float32)
    presence = np.zeros(n, np.float32)
    rows = (
        range(n)
        if progress is None
        else progress(range(n), description="BlazePose landmarks in crops", total=n)
    )
    for i in rows:
        img = images[i][..., ::-1] if rgb else images[i]
        seg = model.segment(np.ascontiguousarray(img), roi)
        lms[i], world[i], presence[i] = seg.landmarks, seg.world_landmarks, seg.presence
    return CropLandmarks(lms, world, presence)
