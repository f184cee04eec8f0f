"""Square person crops that carry their own pinhole camera.

Conventions (see calibration/camera.py): the centre of the top-left pixel is (0, 0), so pixel u
covers [u - 0.5, u + 0.5]. A crop box is given by its *edges* in the undistorted full image:
left edge x0, top edge y0 and side length `side` (pixels, may be fractional or reach outside the
image). Resized to S pixels, crop pixel j covers [x0 + j/s, x0 + (j+1)/s] with s = S / side, so
its centre is at u = x0 + (j + 0.5)/s and

    K_crop = [[fx s, skew s, (cx - x0) s - 0.5],
              [0,    fy s,   (cy - y0) s - 0.5],
              [0,    0,      1]].

Crops are resampled straight from the distorted frame through `cv2.initUndistortRectifyMap`
with K_crop as the new camera matrix, so K_crop together with the camera's R, t describe every
crop pixel exactly, with zero distortion. Parts of the box outside the image are zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration import Camera


@dataclass(frozen=True)
class CropBox:
    """Square crop region in the undistorted full image, by its edges (pixels)."""

    x0: float
    y0: float
    side: float

    def as_array(self) -> np.ndarray:
        return np.array([self.x0, self.y0, self.side], dtype=np.float64)


def hmr_crop_box(box_xyxy: np.ndarray | tuple, scale: float = 1.2) -> CropBox:
    """HMR2 convention: a square of side `scale * max(w, h)` centred on the person box.

    `box_xyxy` = (x0, y0, x1, y1) are box edges in the undistorted full image.
    """
    x0, y0, x1, y1 = (float(v) for v in box_xyxy)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"person box must have x1 > x0 and y1 > y0, got {box_xyxy}")
    if scale <= 0:
        raise ValueError(f"crop scale must be positive, got {scale}")
    side = scale * max(x1 - x0, y1 - y0)
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return CropBox(cx - side / 2, cy - side / 2, side)


def crop_intrinsics(K: np.ndarray, box: CropBox, size: int) -> np.ndarray:
    """Intrinsics of the crop `box` resampled to `size` x `size` pixels (formula in module doc)."""
    s = size / box.side
    K = np.asarray(K, dtype=np.float64)
    Kc = np.array([[K[0, 0] * s, K[0, 1] * s, (K[0, 2] - box.x0) * s - 0.5],
                   [0.0, K[1, 1] * s, (K[1, 2] - box.y0) * s - 0.5],
                   [0.0, 0.0, 1.0]])
    return Kc


def crop_camera(camera: Camera, box: CropBox, size: int) -> Camera:
    """A distortion-free camera (same R, t) that sees exactly what the crop shows."""
    return Camera.create(f"{camera.name}@crop", crop_intrinsics(camera.K, box, size), [],
                         camera.R, camera.t, size, size,
                         meta={"parent": camera.name, "crop_box": box.as_array().tolist()})


def crop_maps(camera: Camera, box: CropBox, size: int,
              src_scale: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Sampling maps (float32, size x size) into a source image of this camera.

    The source may be the full frame shrunk by `src_scale` = (sx, sy) (work-resolution masks);
    pixel centres then map as u_src = (u + 0.5) sx - 0.5.
    """
    Kc = crop_intrinsics(camera.K, box, size)
    dist = camera.dist if camera.dist.size else None
    mapx, mapy = cv2.initUndistortRectifyMap(camera.K, dist, None, Kc, (size, size), cv2.CV_32FC1)
    sx, sy = src_scale
    if (sx, sy) != (1.0, 1.0):
        mapx = (mapx + 0.5) * np.float32(sx) - 0.5
        mapy = (mapy + 0.5) * np.float32(sy) - 0.5
    return mapx, mapy


def resample(image: np.ndarray, mapx: np.ndarray, mapy: np.ndarray, src_per_dst: float,
             interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """`cv2.remap` with anti-aliasing when the crop shrinks the source.

    Only the source region the maps touch is blurred (Gaussian, sigma = (k - 1) / 2 for a
    shrink factor k, as scikit-image does), so a small crop of a 4K frame stays cheap.
    Samples outside the source are zero.
    """
    h, w = image.shape[:2]
    sigma = 0.5 * (src_per_dst - 1.0)
    pad = int(np.ceil(3 * sigma)) + 2 if sigma > 0.25 else 2
    x_lo = max(0, int(np.floor(np.nanmin(mapx))) - pad)
    x_hi = min(w, int(np.ceil(np.nanmax(mapx))) + pad + 1)
    y_lo = max(0, int(np.floor(np.nanmin(mapy))) - pad)
    y_hi = min(h, int(np.ceil(np.nanmax(mapy))) + pad + 1)
    out_shape = mapx.shape + image.shape[2:]
    if x_lo >= x_hi or y_lo >= y_hi:  # the crop lies entirely outside the image
        return np.zeros(out_shape, dtype=image.dtype)
    roi = image[y_lo:y_hi, x_lo:x_hi]
    if sigma > 0.25:
        roi = cv2.GaussianBlur(roi, (0, 0), sigmaX=sigma, sigmaY=sigma,
                               borderType=cv2.BORDER_REPLICATE)
    return cv2.remap(roi, mapx - np.float32(x_lo), mapy - np.float32(y_lo), interpolation,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def extract_crop(image: np.ndarray, camera: Camera, box: CropBox, size: int,
                 src_scale: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """The crop `box` of a (distorted) camera image, undistorted and resized to `size`².

    `image` is the camera's frame, or the frame shrunk by `src_scale` (sx, sy). Multi-channel
    and single-channel images both work; a float mask in [0, 1] gives a coverage crop.
    """
    mapx, mapy = crop_maps(camera, box, size, src_scale)
    src_per_dst = box.side / size * min(src_scale)
    return resample(image, mapx, mapy, src_per_dst)


def undistorted_box(camera: Camera, points_px: np.ndarray, half_pixel: float = 0.5) -> np.ndarray:
    """Edges (x0, y0, x1, y1) in the undistorted image of a set of distorted pixel centres.

    `points_px` are full-resolution pixel centres (e.g. a silhouette's contour); each is taken
    to cover +-`half_pixel` (in full-resolution pixels) around its centre.
    """
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError(f"camera '{camera.name}': cannot box an empty set of pixels")
    if camera.dist.size and np.any(camera.dist):
        xy = camera.undistort_points(pts)
        pts = xy @ camera.K[:2, :2].T + camera.K[:2, 2]
    lo = pts.min(axis=0) - half_pixel
    hi = pts.max(axis=0) + half_pixel
    return np.array([lo[0], lo[1], hi[0], hi[1]])


def mask_outline_full_res(mask: np.ndarray, src_scale: tuple[float, float]) -> tuple[np.ndarray, float]:
    """Outer contour points of a binary mask, as full-resolution pixel centres.

    Returns the points and the half-extent in full-resolution pixels that one mask pixel covers.
    """
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2)), 0.5
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
    sx, sy = src_scale
    full = np.empty_like(pts)
    full[:, 0] = (pts[:, 0] + 0.5) / sx - 0.5
    full[:, 1] = (pts[:, 1] + 0.5) / sy - 0.5
    return full, 0.5 / min(sx, sy)
