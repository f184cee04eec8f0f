"""Where a person whom only one camera sees stands: a rough 3D skeleton from one view.

One view gives each landmark's ray, not its depth. People stand on the floor, though, and the
people whom several cameras see tell at what height above it their ankles are. The ray through
a single-view person's ankles meets that height where they stand; their other landmarks are put
where their rays cross the upright plane through that point that faces the camera. The guess is
good to the body's own depth (a few decimetres), enough to say where to look for them in the
other cameras (`CrowdTracker` looks there with the landmark model, and a person found in two
cameras is triangulated from those views: the guess never becomes a skeleton of its own).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from calibration.camera import Camera
from gst.data.keypoints.geometry import viewing_rays
from gst.data.keypoints.instances import PersonInstance

ANKLES = (27, 28)


class AnkleHeight:
    """Running median height (along `up`) of the triangulated people's ankles, in metres (None
    until four ankles were seen: two people of one frame)."""

    def __init__(self, up, keep: int = 300):
        self.up = np.asarray(up, np.float64)
        self._heights: deque[float] = deque(maxlen=keep)

    def add(self, skeleton: np.ndarray) -> None:
        h = np.asarray(skeleton, np.float64)[list(ANKLES)] @ self.up
        self._heights.extend(float(x) for x in h[np.isfinite(h)])

    @property
    def value(self) -> float | None:
        return float(np.median(self._heights)) if len(self._heights) >= 4 else None


def standing_skeleton(
    cam: Camera, instance: PersonInstance, up, ankle_height: float, min_confidence: float
) -> np.ndarray | None:
    """(33, 3) world landmarks of a person seen in `cam` alone, read as standing with their
    ankles at `ankle_height` (NaN where a landmark is under `min_confidence`); None when their
    ankles are not seen, their ray does not come down to that height in front of the camera, or
    they stand straight below it."""
    up = np.asarray(up, np.float64)
    lm = instance.landmarks
    seen = lm[:, 2] >= min_confidence
    ankles = [a for a in ANKLES if seen[a]]
    if not ankles or seen.sum() < 8:
        return None
    c = cam.center
    feet = viewing_rays(cam, lm[ankles, :2].mean(axis=0))
    down = feet @ up
    if down >= -1e-6:
        return None  # the ray does not come down to the floor
    s = (ankle_height - c @ up) / down
    if s <= 0:
        return None
    stand = c + s * feet
    # the upright plane through the ankles, facing the camera
    normal = (stand - c) - ((stand - c) @ up) * up
    across = float(np.linalg.norm(normal))
    if across < 1e-9:
        return None  # straight below the camera: no upright plane faces it (all NaN before)
    normal /= across
    rays = viewing_rays(cam, lm[:, :2])
    along = rays @ normal
    t = np.where(along > 1e-6, ((stand - c) @ normal) / np.where(along > 1e-6, along, 1), np.nan)
    out = c + t[:, None] * rays
    out[~seen | ~np.isfinite(t)] = np.nan
    return out
