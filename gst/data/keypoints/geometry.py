"""Multi-view geometry of landmarks: viewing rays, how close two rays pass, weighted
triangulation and reprojection.

Two detections of one landmark in two calibrated cameras are consistent when their viewing rays
(nearly) meet. The distance between the rays, in metres, is the symmetric epipolar distance
measured at the person rather than in pixels (an epipolar distance of e pixels at depth z is
about e z / f metres), so one threshold fits any resolution and any distance to the camera.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.camera import FIELD_MARGIN, Camera


def viewing_rays(cam: Camera, pixels: np.ndarray, exact_only: bool = False) -> np.ndarray:
    """(..., 2) distorted pixels -> (..., 3) unit world directions from the camera centre
    (undistorted with cv2.undistortPoints through `Camera.unproject`; `exact_only`: NaN for a
    pixel beyond where the lens model inverts)."""
    px = np.asarray(pixels, dtype=np.float64)
    shape = px.shape[:-1]
    flat = px.reshape(-1, 2)
    if len(flat) == 0:
        return np.zeros((*shape, 3))
    return cam.unproject(flat, exact_only=exact_only).reshape(*shape, 3)


def ray_gaps(
    c1: np.ndarray, d1: np.ndarray, c2: np.ndarray, d2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest approach of rays c1 + s d1 and c2 + t d2 (unit directions, broadcasting).

    Returns (gap in metres, midpoint of the closest points (..., 3), s, t): s and t are the
    distances along each ray (negative = behind that camera). Parallel rays give the distance
    between the lines and the midpoint at s = 0.
    """
    w0 = c1 - c2
    b = np.sum(d1 * d2, axis=-1)
    d = np.sum(d1 * w0, axis=-1)
    e = np.sum(d2 * w0, axis=-1)
    denom = 1.0 - b * b
    ok = denom > 1e-10
    safe = np.where(ok, denom, 1.0)
    s = np.where(ok, (b * e - d) / safe, 0.0)
    t = np.where(ok, (e - b * d) / safe, e)
    p1 = c1 + s[..., None] * d1
    p2 = c2 + t[..., None] * d2
    return np.linalg.norm(p1 - p2, axis=-1), 0.5 * (p1 + p2), s, t


def triangulate_weighted(
    cams: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Weighted linear triangulation of L points seen by V cameras.

    pixels (V, L, 2) distorted; weights (V, L) (0 = not seen). Each view adds the two DLT rows
    x P3 - P1, y P3 - P2 in undistorted normalised coordinates, scaled by its weight; one
    batched SVD solves all points. Points with fewer than two weighted views are NaN.
    """
    V, L = weights.shape
    xy = np.zeros((V, L, 2))
    weights = np.array(weights, dtype=np.float64)
    for v, cam in enumerate(cams):
        seen = weights[v] > 0
        if seen.any():
            # a pixel beyond where the lens model inverts has no ray: not seen
            xy[v, seen] = cam.undistort_points(pixels[v, seen], exact_only=True)
    lost = ~np.isfinite(xy).all(-1)
    xy[lost], weights[lost] = 0.0, 0.0
    P = np.stack([np.hstack([c.R, c.t[:, None]]) for c in cams])  # (V, 3, 4)
    w = weights[..., None]
    rows_x = (xy[..., 0:1] * P[:, None, 2, :] - P[:, None, 0, :]) * w  # (V, L, 4)
    rows_y = (xy[..., 1:2] * P[:, None, 2, :] - P[:, None, 1, :]) * w
    A = np.transpose(np.concatenate([rows_x, rows_y], axis=0), (1, 0, 2))  # (L, 2V, 4)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[(weights > 0).sum(axis=0) < 2] = np.nan
    return X


def project(
    cam: Camera, points: np.ndarray, margin: float = FIELD_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """(L, 3) world points (NaN allowed) -> ((L, 2) distorted pixels, (L,) in front of the
    camera). Points that are NaN, behind the camera, or whose pinhole projection lies more than
    `margin` x the image's size outside it give NaN pixels."""
    out = np.full((len(points), 2), np.nan)
    ok = np.all(np.isfinite(points), axis=1)
    front = np.zeros(len(points), bool)
    if ok.any():
        front[ok] = cam.to_camera(points[ok])[:, 2] > 1e-3
        seen = np.zeros(len(points), bool)
        seen[ok] = cam.in_field(points[ok], margin)
        if seen.any():
            out[seen] = cam.project(points[seen])
    return out, front
