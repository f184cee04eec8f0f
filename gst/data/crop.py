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

Tracking uses the same geometry through `CropWindow`, which states a crop in the detector's
pixel-CORNER convention (pixel column i spans [i, i + 1), so a box around columns 10..19 is
x0 = 10, x1 = 20): a window (x0, y0, side) is the `CropBox` (x0 - 0.5, y0 - 0.5, side), and a
full-frame point u maps to the crop point u' = (u - x0 + 0.5) s - 0.5. Points (projections,
joints2d, K's principal point) always use the pixel-centre convention.
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


CROP_ENLARGE = 1.2  # HMR2: the square side is 1.2 x the longer side of the person box


@dataclass(frozen=True)
class CropWindow:
    """A square window of the frame in the pixel-corner convention, resized to `size` pixels."""

    x0: float
    y0: float
    side: float
    size: int

    @property
    def scale(self) -> float:
        """Crop pixels per frame pixel."""
        return self.size / self.side

    @property
    def box(self) -> CropBox:
        """The same region as a `CropBox` (pixel-centre convention edges)."""
        return CropBox(self.x0 - 0.5, self.y0 - 0.5, self.side)

    def affine(self) -> np.ndarray:
        """(2, 3) map of frame points to crop points, both in the pixel-centre convention."""
        s = self.scale
        return np.array([[s, 0.0, s * (0.5 - self.x0) - 0.5], [0.0, s, s * (0.5 - self.y0) - 0.5]])

    def to_crop(self, uv: np.ndarray) -> np.ndarray:
        """Frame points (N, 2) -> crop points (N, 2), pixel-centre convention."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return (uv - [self.x0, self.y0] + 0.5) * self.scale - 0.5

    def to_frame(self, uv_crop: np.ndarray) -> np.ndarray:
        """Crop points (N, 2) -> frame points (N, 2), pixel-centre convention."""
        uv_crop = np.asarray(uv_crop, dtype=np.float64).reshape(-1, 2)
        return (uv_crop + 0.5) / self.scale + [self.x0, self.y0] - 0.5


def hmr_crop_box(box_xyxy: np.ndarray | tuple, scale: float = 1.2) -> CropBox:
    """HMR2 convention: a square of side `scale * max(w, h)` centred on the person box.

    `box_xyxy` = (x0, y0, x1, y1) are box edges in the undistorted full image.
    """
    x0, y0, x1, y1 = (float(v) for v in np.asarray(box_xyxy, dtype=np.float64).reshape(4))
    if not (np.isfinite([x0, y0, x1, y1]).all() and x1 > x0 and y1 > y0):
        raise ValueError(
            f"person box must be finite with x1 > x0 and y1 > y0, got {[x0, y0, x1, y1]}"
        )
    if scale <= 0:
        raise ValueError(f"crop scale must be positive, got {scale}")
    side = scale * max(x1 - x0, y1 - y0)
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return CropBox(cx - side / 2, cy - side / 2, side)


def crop_window(box_xyxy, size: int = 256, enlarge: float = CROP_ENLARGE) -> CropWindow:
    """The HMR2 window (see `hmr_crop_box`) of a corner-convention box, resized to `size`."""
    if size <= 0:
        raise ValueError(f"crop size must be positive, got {size}")
    b = hmr_crop_box(np.asarray(box_xyxy, dtype=np.float64).reshape(4) - 0.5, enlarge)
    return CropWindow(b.x0 + 0.5, b.y0 + 0.5, b.side, int(size))


def crop_intrinsics(
    K: np.ndarray, box: CropBox | CropWindow, size: int | None = None
) -> np.ndarray:
    """Intrinsics of the crop `box` resampled to `size` x `size` pixels (formula in module doc).

    A `CropWindow` carries its own size (pass none)."""
    if isinstance(box, CropWindow):
        box, size = box.box, box.size if size is None else size
    if size is None:
        raise ValueError("crop_intrinsics of a CropBox needs the crop size")
    s = size / box.side
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    Kc = np.array(
        [
            [K[0, 0] * s, K[0, 1] * s, (K[0, 2] - box.x0) * s - 0.5],
            [0.0, K[1, 1] * s, (K[1, 2] - box.y0) * s - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    return Kc


def crop_camera(camera: Camera, box: CropBox, size: int) -> Camera:
    """A distortion-free camera (same R, t) that sees exactly what the crop shows."""
    return Camera.create(
        f"{camera.name}@crop",
        crop_intrinsics(camera.K, box, size),
        [],
        camera.R,
        camera.t,
        size,
        size,
        meta={"parent": camera.name, "crop_box": box.as_array().tolist()},
    )


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


def distortion_maps(
    camera: Camera, K_crop: np.ndarray, size: int, step: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of an ideal size x size camera with intrinsics K_crop, the raw-frame
    pixel it sees (float32 maps for cv2.remap). The lens model is evaluated exactly
    (cv2.projectPoints) on a grid every `step` pixels and interpolated bilinearly in between:
    far cheaper than all size^2 pixels and, lens distortion being smooth, within a few
    hundredths of a pixel of cv2.initUndistortRectifyMap."""
    grid, i, w = _interpolation_weights(size, step)
    gu, gv = np.meshgrid(grid, grid)
    fx, s, cx = K_crop[0]
    fy, cy = K_crop[1, 1], K_crop[1, 2]
    y = (gv - cy) / fy
    x = (gu - cx - s * y) / fx
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.lens_K(), camera.dist)
    uv = camera.with_skew(uv.reshape(len(grid), len(grid), 2))
    return _bilinear(uv[..., 0], i, w).astype(np.float32), _bilinear(uv[..., 1], i, w).astype(
        np.float32
    )


def crop_maps(
    camera: Camera,
    box: CropBox,
    size: int,
    src_scale: tuple[float, float] = (1.0, 1.0),
    grid_step: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sampling maps (float32, size x size) into a source image of this camera.

    The source may be the full frame shrunk by `src_scale` = (sx, sy) (work-resolution masks);
    pixel centres then map as u_src = (u + 0.5) sx - 0.5. With `grid_step` the lens model is
    evaluated on that grid and interpolated (`distortion_maps`, the fast path of tracking);
    otherwise every pixel goes through cv2.initUndistortRectifyMap.
    """
    Kc = crop_intrinsics(camera.K, box, size)
    if grid_step is not None and camera.dist.size and np.any(camera.dist):
        mapx, mapy = distortion_maps(camera, Kc, size, grid_step)
    else:
        dist = camera.dist if camera.dist.size else None
        mapx, mapy = cv2.initUndistortRectifyMap(
            camera.lens_K(), dist, None, Kc, (size, size), cv2.CV_32FC1
        )
        if camera.skew:  # OpenCV's maps are without it (`Camera.lens_K`)
            uv = camera.with_skew(np.stack([mapx, mapy], -1))
            mapx, mapy = uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32)
    sx, sy = src_scale
    if (sx, sy) != (1.0, 1.0):
        mapx = (mapx + 0.5) * np.float32(sx) - 0.5
        mapy = (mapy + 0.5) * np.float32(sy) - 0.5
    return mapx, mapy


def folded_pixels(mapx: np.ndarray, mapy: np.ndarray) -> np.ndarray:
    """(S, S) bool: crop pixels whose rays lie beyond the radius where the lens model folds
    (a strong barrel polynomial's distorted radius peaks, then shrinks). It maps them back into
    the image onto pixels that nearer rays own, so they would show a mirrored copy of the frame
    instead of nothing; there the map reverses orientation (Jacobian determinant <= 0)."""
    if min(mapx.shape) < 2:
        return np.zeros(mapx.shape, bool)
    dxdv, dxdu = np.gradient(mapx.astype(np.float64))
    dydv, dydu = np.gradient(mapy.astype(np.float64))
    return ~(dxdu * dydv - dxdv * dydu > 0)  # NaN maps count as folded


ANTIALIAS = ("gaussian", "pyramid")


def resample(
    image: np.ndarray,
    mapx: np.ndarray,
    mapy: np.ndarray,
    src_per_dst: float,
    interpolation: int = cv2.INTER_LINEAR,
    antialias: str = "gaussian",
) -> np.ndarray:
    """`cv2.remap` with anti-aliasing when the crop shrinks the source.

    Only the source region the maps touch is filtered, so a small crop of a 4K frame stays
    cheap. "gaussian" blurs it with sigma = (k - 1) / 2 for a shrink factor k (as scikit-image
    does; the most faithful); "pyramid" halves it with cv2.pyrDown until the shrink is at most
    2 (several times cheaper for big shrinks; tracking uses it). Samples outside the source are
    zero.
    """
    if antialias == "pyramid":
        return _resample_pyramid(image, mapx, mapy, src_per_dst, interpolation)
    if antialias != "gaussian":
        raise ValueError(f"antialias must be one of {ANTIALIAS}, got '{antialias}'")
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
        roi = cv2.GaussianBlur(
            roi, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE
        )
    return cv2.remap(
        roi,
        mapx - np.float32(x_lo),
        mapy - np.float32(y_lo),
        interpolation,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def _pyramid_levels(src_per_dst: float) -> int:
    levels = 0
    while src_per_dst / (2**levels) > 2.0:
        levels += 1
    return levels


def _pyramid_roi(
    image: np.ndarray, x_lo: float, y_lo: float, x_hi: float, y_hi: float, levels: int
) -> tuple[np.ndarray, float, float, float]:
    """The part of `image` over the source-pixel range [lo, hi], halved `levels` times with
    cv2.pyrDown. Returns (roi, offset_x, offset_y, factor): a source pixel centre u sits at
    (u - offset_x) / factor in the roi, in the roi's corner convention (see callers)."""
    margin = 3 * 2**levels  # keeps pyrDown's border reflection outside the sampled region
    h, w = image.shape[:2]
    rx0 = max(int(np.floor(x_lo)) - margin, 0)
    ry0 = max(int(np.floor(y_lo)) - margin, 0)
    rx1 = min(int(np.ceil(x_hi)) + margin, w)
    ry1 = min(int(np.ceil(y_hi)) + margin, h)
    if rx1 <= rx0 or ry1 <= ry0:  # entirely outside the frame
        return image[:1, :1] * 0, 0.0, 0.0, 1.0
    roi = image[ry0:ry1, rx0:rx1]
    for _ in range(levels):
        roi = cv2.pyrDown(roi)
    return roi, float(rx0), float(ry0), float(2**levels)


def _resample_pyramid(image, mapx, mapy, src_per_dst, interpolation):
    roi, ox, oy, f = _pyramid_roi(
        image,
        float(np.nanmin(mapx)),
        float(np.nanmin(mapy)),
        float(np.nanmax(mapx)) + 1,
        float(np.nanmax(mapy)) + 1,
        _pyramid_levels(src_per_dst),
    )
    if f != 1.0 or ox or oy:
        mapx = (mapx - np.float32(ox)) / np.float32(f)
        mapy = (mapy - np.float32(oy)) / np.float32(f)
    return cv2.remap(roi, mapx, mapy, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def cut_crop(
    image: np.ndarray, window: CropWindow, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Resample `window` of a distortion-free `image` (H, W[, C]) to size x size: one affine
    warp after pyramid anti-aliasing (the pinhole fast path of tracking); zero outside the frame."""
    levels = _pyramid_levels(window.side / window.size)
    roi, ox, oy, f = _pyramid_roi(
        image, window.x0, window.y0, window.x0 + window.side, window.y0 + window.side, levels
    )
    s = window.scale * f  # crop pixels per roi pixel
    # roi point r = (u - ox) / f; crop point u' = (u - x0 + 0.5) * scale - 0.5
    #   = (f r + ox - x0 + 0.5) * scale - 0.5 = s r + s (ox - x0 + 0.5) / f - 0.5
    M = np.array(
        [
            [s, 0.0, s * ((ox - window.x0) / f + 0.5 / f) - 0.5],
            [0.0, s, s * ((oy - window.y0) / f + 0.5 / f) - 0.5],
        ]
    )
    return cv2.warpAffine(
        roi,
        M,
        (window.size, window.size),
        flags=interpolation,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def cut_undistorted_crop(
    image: np.ndarray, camera: Camera, window: CropWindow, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Crop `window` of the UNDISTORTED image (same K as `camera`) straight from the distorted
    `image` in one remap, with interpolated lens maps and pyramid anti-aliasing (tracking's
    fast path of `extract_crop`). `window` is in undistorted-image coordinates."""
    mapx, mapy = crop_maps(camera, window.box, window.size, grid_step=8)
    # Bound the window in the distorted frame by the maps themselves (a square of their span).
    x_lo, y_lo = float(mapx.min()) + 0.5, float(mapy.min()) + 0.5
    span = max(float(mapx.max() - mapx.min()), float(mapy.max() - mapy.min()), 1.0)
    roi, ox, oy, f = _pyramid_roi(
        image, x_lo, y_lo, x_lo + span, y_lo + span, _pyramid_levels(span / window.size)
    )
    if f != 1.0 or ox or oy:
        mapx = (mapx - np.float32(ox)) / np.float32(f)
        mapy = (mapy - np.float32(oy)) / np.float32(f)
    return cv2.remap(roi, mapx, mapy, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def extract_crop(
    image: np.ndarray,
    camera: Camera,
    box: CropBox,
    size: int,
    src_scale: tuple[float, float] = (1.0, 1.0),
) -> np.ndarray:
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
    to cover +-`half_pixel` (in full-resolution pixels) around its centre. Pixels beyond the
    radius where the lens model can be inverted (`Camera.undistort_points`' `exact_only`: a
    landmark box reaching far outside the frame) are no evidence and are left out; the
    iteration's answer there lay up to 1,600 px from any ray and widened the box sixfold.
    """
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError(f"camera '{camera.name}': cannot box an empty set of pixels")
    if camera.dist.size and np.any(camera.dist):
        xy = camera.undistort_points(pts, exact_only=True)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if len(xy) == 0:
            raise ValueError(
                f"camera '{camera.name}': none of the {len(pts)} pixels to box lies where the "
                "lens model can be inverted"
            )
        pts = xy @ camera.K[:2, :2].T + camera.K[:2, 2]
    lo = pts.min(axis=0) - half_pixel
    hi = pts.max(axis=0) + half_pixel
    return np.array([lo[0], lo[1], hi[0], hi[1]])


def mask_outline_full_res(
    mask: np.ndarray, src_scale: tuple[float, float]
) -> tuple[np.ndarray, float]:
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
