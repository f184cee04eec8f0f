"""Person instances seen by one camera: 2D landmarks with confidences, a box, an optional mask.

Landmarks follow BlazePose's 33-point layout (MediaPipe order) in the camera's DISTORTED image
pixels (as a detector sees the frame; OpenCV convention, pixel centres at integers), with a
confidence in [0, 1] per landmark. A landmark that is NaN, infinite or has a confidence that is
not a number counts as unseen (confidence 0); that is the only clean-up done here, so a broken
detector output never reaches the geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_LANDMARKS = 33
# BlazePose landmarks used to tell people apart: nose, ears, shoulders, elbows, wrists, hips,
# knees, ankles, heels, toes. Face points cluster in the head (they would outvote the body)
# and the hand points are noisy.
BODY_LANDMARKS = (0, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32)
# Left/right partners (BlazePose index order), for detectors that mirror a person.
LEFT_RIGHT = (
    (1, 4),
    (2, 5),
    (3, 6),
    (7, 8),
    (9, 10),
    (11, 12),
    (13, 14),
    (15, 16),
    (17, 18),
    (19, 20),
    (21, 22),
    (23, 24),
    (25, 26),
    (27, 28),
    (29, 30),
    (31, 32),
)
MIRROR = np.arange(N_LANDMARKS)
for _a, _b in LEFT_RIGHT:
    MIRROR[_a], MIRROR[_b] = _b, _a


class InstanceError(ValueError):
    """A person instance is malformed; the message says which field and what was expected."""


@dataclass(frozen=True, eq=False)
class PersonInstance:
    """One person found in one camera's frame. Build with `PersonInstance.create`."""

    landmarks: np.ndarray  # (33, 3) float64: u, v distorted pixels, confidence (0 = unseen)
    box: np.ndarray  # (4,) x0, y0, x1, y1 in distorted pixels (pixel edges)
    score: float = 1.0  # detector's confidence that a person is there
    mask: np.ndarray | None = None  # optional (H, W) bool or uint8 person mask

    @classmethod
    def create(
        cls,
        landmarks,
        box=None,
        score: float = 1.0,
        mask: np.ndarray | None = None,
        where: str = "instance",
    ) -> PersonInstance:
        """Validate and clean one instance. `box` defaults to the seen landmarks' extent; `where`
        names the instance in errors (e.g. "camera cam01, frame 12, instance 2")."""
        lm = np.array(landmarks, dtype=np.float64, copy=True)
        if lm.shape != (N_LANDMARKS, 3):
            raise InstanceError(
                f"{where}: landmarks have shape {lm.shape}, expected ({N_LANDMARKS}, 3) "
                "(u, v in distorted pixels, confidence)"
            )
        bad = ~np.all(np.isfinite(lm), axis=1)
        lm[bad] = 0.0  # unseen: no position, no confidence
        lm[:, 2] = np.clip(lm[:, 2], 0.0, 1.0)
        if box is None:
            seen = lm[:, 2] > 0
            if seen.any():
                lo, hi = lm[seen, :2].min(axis=0), lm[seen, :2].max(axis=0)
                box = (lo[0] - 0.5, lo[1] - 0.5, hi[0] + 0.5, hi[1] + 0.5)
            else:
                box = (np.nan,) * 4
        b = np.asarray(box, dtype=np.float64).reshape(-1)
        if b.shape != (4,):
            raise InstanceError(f"{where}: box has {b.size} values, expected 4 (x0, y0, x1, y1)")
        if not np.all(np.isfinite(b)):
            # a box with a NaN or inf is no box (all NaN: the size comes from the landmarks); an
            # inf side made every skeleton fit the instance, a NaN one a size of the other side
            b = np.full(4, np.nan)
        if mask is not None and np.ndim(mask) != 2:
            raise InstanceError(f"{where}: mask must be a 2D image, got shape {np.shape(mask)}")
        s = float(score)
        return cls(lm, b, s if np.isfinite(s) else 0.0, mask)

    @property
    def confidence(self) -> np.ndarray:
        return self.landmarks[:, 2]

    @property
    def n_seen(self) -> int:
        return int(np.count_nonzero(self.landmarks[:, 2] > 0))

    @property
    def scale(self) -> float:
        """Size of the person in pixels: the longer side of the box (NaN without a box)."""
        b = self.box
        return float(max(b[2] - b[0], b[3] - b[1]))
