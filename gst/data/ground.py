"""A detection box read as a person standing on the floor, using the calibration.

The ray through the box's bottom centre meets the ground plane (the feet); the ray through its
top centre, where it passes the vertical line through the feet, gives the person's height.
Boxes implying an implausible height (a lone limb, a shadow, a box around two people) can then
be rejected: a use of the calibration no 2D detector has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration import Camera


@dataclass(frozen=True)
class GroundSeed:
    """A detection read as a person standing on the floor."""

    camera: str
    frame: int
    ground: np.ndarray  # (3,) world point on the floor under the person
    height: float  # metres
    score: float


def _ray(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """World direction of the ray through distorted pixel centres (N, 2)."""
    xy = camera.undistort_points(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d = d_cam @ camera.R  # R^T d for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ground_seed(
    camera: Camera,
    box_full: np.ndarray,
    up: np.ndarray,
    floor: float = 0.0,
    frame: int = -1,
    score: float = 1.0,
) -> GroundSeed | None:
    """The person a full-resolution box (corner convention) shows, standing on the plane
    up . X = floor; None when the feet ray misses the floor in front of the camera."""
    up = np.asarray(up, dtype=np.float64)
    x0, y0, x1, y1 = np.asarray(box_full, dtype=np.float64)
    cx = 0.5 * (x0 + x1) - 0.5
    feet, head = _ray(camera, np.array([[cx, y1 - 0.5], [cx, y0 - 0.5]]))
    c = camera.center
    denom = feet @ up
    if abs(denom) < 1e-9:
        return None
    s = (floor - c @ up) / denom
    if s <= 0:
        return None
    g = c + s * feet
    # Height: the point of the vertical line g + h up nearest to the head ray c + t head.
    a = np.stack([up, -head], axis=1)
    sol, *_ = np.linalg.lstsq(a, c - g, rcond=None)
    return GroundSeed(camera.name, int(frame), g, float(sol[0]), float(score))
