"""Projection helpers that stay valid with lens distortion.

OpenCV's distortion polynomial folds back far outside the image, so a point well out of view
can project to a pixel inside it. `project_in_view` only trusts points whose undistorted
direction lies within the field the image covers.
"""

from __future__ import annotations

import numpy as np

from calibration import Camera


def field_radius(camera: Camera) -> float:
    """Largest undistorted normalised radius seen by the image (at its border)."""
    w, h = camera.width, camera.height
    t = np.linspace(0, 1, 33)
    border = np.concatenate(
        [
            np.c_[t * (w - 1), np.zeros_like(t)],
            np.c_[t * (w - 1), np.full_like(t, h - 1)],
            np.c_[np.zeros_like(t), t * (h - 1)],
            np.c_[np.full_like(t, w - 1), t * (h - 1)],
        ]
    )
    xy = camera.undistort_points(border)
    return float(np.linalg.norm(xy, axis=1).max())


def project_in_view(
    camera: Camera, points: np.ndarray, radius: float | None = None, near: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of world points and a mask (N,) of those really in view: in front
    of the camera, inside the covered field and inside the image. Pixels are NaN where the
    point is behind the camera or outside the covered field."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam_pts = camera.to_camera(pts)
    z = cam_pts[:, 2]
    radius = field_radius(camera) if radius is None else radius
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.linalg.norm(cam_pts[:, :2] / z[:, None], axis=1)
    valid = (z > near) & (r <= radius * 1.05)
    uv = np.full((len(pts), 2), np.nan)
    if valid.any():
        uv[valid] = camera.project(pts[valid])
    inside = (
        valid
        & (uv[:, 0] >= -0.5)
        & (uv[:, 0] < camera.width - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] < camera.height - 0.5)
    )
    return uv, inside
