"""Square person crops and their intrinsics (the HMR2 crop convention).

Coordinate conventions (they differ on purpose, as in most detectors and OpenCV):
- Boxes and crop windows use the pixel-CORNER convention: pixel column i spans [i, i + 1), so a
  box around columns 10..19 is x0 = 10, x1 = 20 and its width is x1 - x0.
- Points (projections, joints2d, K's principal point) use OpenCV's pixel-CENTRE convention:
  the centre of pixel i is at u = i.

A window (x0, y0, side) resized to S pixels has scale s = S / side and maps a full-frame point u
to the crop point u' = (u - x0 + 0.5) * s - 0.5; K_crop is K with the same scale and shift.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration import Camera

CROP_ENLARGE = 1.2  # HMR2: the square side is 1.2 x the longer side of the detection box


@dataclass(frozen=True)
class CropWindow:
    """A square window of the frame (corner convention), resized to `size` x `size` pixels."""

    x0: float
    y0: float
    side: float
    size: int

    @property
    def scale(self) -> float:
        """Crop pixels per frame pixel."""
        return self.size / self.side

    def affine(self) -> np.ndarray:
        """(2, 3) map of frame points to crop points, both in the pixel-centre convention."""
        s = self.scale
        return np.array([[s, 0.0, s * (0.5 - self.x0) - 0.5],
                         [0.0, s, s * (0.5 - self.y0) - 0.5]])

    def to_crop(self, uv: np.ndarray) -> np.ndarray:
        """Frame points (N, 2) -> crop points (N, 2), pixel-centre convention."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return (uv - [self.x0, self.y0] + 0.5) * self.scale - 0.5

    def to_frame(self, uv_crop: np.ndarray) -> np.ndarray:
        """Crop points (N, 2) -> frame points (N, 2), pixel-centre convention."""
        uv_crop = np.asarray(uv_crop, dtype=np.float64).reshape(-1, 2)
        return (uv_crop + 0.5) / self.scale + [self.x0, self.y0] - 0.5


def crop_window(box_xyxy, size: int = 256, enlarge: float = CROP_ENLARGE) -> CropWindow:
    """The square window centred on `box_xyxy` (corner convention) with side enlarge * max(w, h)."""
    x0, y0, x1, y1 = (float(v) for v in np.asarray(box_xyxy, dtype=np.float64).reshape(4))
    w, h = x1 - x0, y1 - y0
    if not (np.isfinite([x0, y0, x1, y1]).all() and w > 0 and h > 0):
        raise ValueError(f"box must be finite with x1 > x0 and y1 > y0, got {[x0, y0, x1, y1]}")
    if size <= 0:
        raise ValueError(f"crop size must be positive, got {size}")
    side = enlarge * max(w, h)
    return CropWindow(0.5 * (x0 + x1) - 0.5 * side, 0.5 * (y0 + y1) - 0.5 * side, side, int(size))


def crop_intrinsics(K: np.ndarray, window: CropWindow) -> np.ndarray:
    """Intrinsics of the crop: u' = (u - x0 + 0.5) s - 0.5 applied to the rows of K."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    A = np.vstack([window.affine(), [0.0, 0.0, 1.0]])
    return A @ K


def _pyramid_roi(image: np.ndarray, window: CropWindow) -> tuple[np.ndarray, float, float, float]:
    """The part of `image` under `window`, halved with cv2.pyrDown until the crop scale is at
    least 1/2, so bilinear resampling does not alias. Returns (roi, offset_x, offset_y, factor):
    a frame point u sits at (u - offset_x) / factor in the roi."""
    levels = 0
    while window.scale * (2 ** levels) < 0.5:
        levels += 1
    margin = 3 * 2 ** levels  # keeps pyrDown's border reflection outside the window
    h, w = image.shape[:2]
    rx0 = max(int(np.floor(window.x0)) - margin, 0)
    ry0 = max(int(np.floor(window.y0)) - margin, 0)
    rx1 = min(int(np.ceil(window.x0 + window.side)) + margin, w)
    ry1 = min(int(np.ceil(window.y0 + window.side)) + margin, h)
    if rx1 <= rx0 or ry1 <= ry0:  # window entirely outside the frame
        return image[:1, :1] * 0, 0.0, 0.0, 1.0
    roi = image[ry0:ry1, rx0:rx1]
    for _ in range(levels):
        roi = cv2.pyrDown(roi)
    return roi, float(rx0), float(ry0), float(2 ** levels)


def cut_crop(image: np.ndarray, window: CropWindow, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Resample `window` of `image` (H, W[, C]) to size x size; zero outside the frame."""
    roi, ox, oy, f = _pyramid_roi(image, window)
    s = window.scale * f  # crop pixels per roi pixel
    M = np.array([[s, 0.0, s * ((ox - window.x0) / f + 0.5 / f) - 0.5],
                  [0.0, s, s * ((oy - window.y0) / f + 0.5 / f) - 0.5]])
    # roi point r = (u - ox) / f; crop point u' = (u - x0 + 0.5) * scale - 0.5
    #   = (f r + ox - x0 + 0.5) * scale - 0.5 = s r + s (ox - x0 + 0.5) / f - 0.5
    return cv2.warpAffine(roi, M, (window.size, window.size), flags=interpolation,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _interpolation_weights(size: int, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid coordinates 0, step, ... (covering size - 1), and for every integer coordinate the
    index of the grid cell it falls in and its weight towards the cell's far end."""
    n = -(-(size - 1) // step) + 1
    grid = np.arange(n, dtype=np.float64) * step
    u = np.arange(size, dtype=np.float64)
    i = np.minimum((u // step).astype(int), n - 2)
    return grid, i, (u - grid[i]) / step


def _bilinear(values: np.ndarray, i: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Upsample (n, n) grid values to (size, size) by separable linear interpolation (gathers
    and multiplies only: tiny BLAS calls stall when the machine is oversubscribed)."""
    rows = values[i] * (1 - w)[:, None] + values[i + 1] * w[:, None]
    return rows[:, i] * (1 - w)[None, :] + rows[:, i + 1] * w[None, :]


def distortion_maps(camera: Camera, K_crop: np.ndarray, size: int, step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of an ideal (undistorted) size x size camera with intrinsics K_crop, the
    raw-frame pixel it sees: float32 maps for cv2.remap. The lens model is evaluated exactly
    (cv2.projectPoints) on a grid every `step` pixels and interpolated bilinearly in between,
    which is far cheaper than evaluating all size^2 pixels and, lens distortion being smooth,
    agrees with cv2.initUndistortRectifyMap to a few hundredths of a pixel."""
    grid, i, w = _interpolation_weights(size, step)
    gu, gv = np.meshgrid(grid, grid)
    fx, s, cx = K_crop[0]
    fy, cy = K_crop[1, 1], K_crop[1, 2]
    y = (gv - cy) / fy
    x = (gu - cx - s * y) / fx
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    uv = uv.reshape(len(grid), len(grid), 2)
    return _bilinear(uv[..., 0], i, w).astype(np.float32), _bilinear(uv[..., 1], i, w).astype(np.float32)


def cut_undistorted_crop(image: np.ndarray, camera: Camera, window: CropWindow,
                         interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Crop `window` of the UNDISTORTED image (same K as `camera`) straight from the distorted
    `image`, in one remap: each crop pixel is traced through K_crop to a ray and distorted with
    the camera's lens model. `window` is in undistorted-image coordinates."""
    map_x, map_y = distortion_maps(camera, crop_intrinsics(camera.K, window), window.size)
    # Antialias through the pyramid: bound the window in the distorted frame by the map itself.
    xs, ys = map_x.ravel(), map_y.ravel()
    span = max(float(xs.max() - xs.min()), float(ys.max() - ys.min()), 1.0)
    bound = CropWindow(float(xs.min()) + 0.5, float(ys.min()) + 0.5, span, window.size)
    roi, ox, oy, f = _pyramid_roi(image, bound)
    if f != 1.0 or ox or oy:
        map_x = (map_x - ox) / f
        map_y = (map_y - oy) / f
    return cv2.remap(roi, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
