"""Per-camera intrinsics from board views (cv2.calibrateCamera), with outlier views rejected,
and per-view board poses (cv2.solvePnP)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.board import BoardSpec, FrameDetection
from calibration.errors import CalibrationError

# Lens models we solve for; each maps 1:1 to a COLMAP camera model for bundle adjustment.
LENS_MODELS = {
    "pinhole": ("PINHOLE", 0),  # no distortion
    "opencv": ("OPENCV", 4),  # k1, k2, p1, p2 (stored as 5 terms with k3 = 0)
    "full_opencv": ("FULL_OPENCV", 8),  # k1, k2, p1, p2, k3, k4, k5, k6 (rational)
}


class IntrinsicsError(CalibrationError):
    """A camera's intrinsics cannot be estimated from its board views."""


@dataclass
class Intrinsics:
    """One camera's intrinsics and the views that produced them."""

    camera: str
    K: np.ndarray
    dist: np.ndarray  # OpenCV order, 5 terms for 'opencv'/'pinhole', 8 for 'full_opencv'
    rms_px: float  # calibrateCamera RMS over the kept views
    frames_used: list[int] = field(default_factory=list)
    frames_rejected: list[int] = field(default_factory=list)


def _calib_flags(lens_model: str) -> int:
    if lens_model not in LENS_MODELS:
        raise IntrinsicsError(
            f"lens model '{lens_model}' is unknown, expected one of {sorted(LENS_MODELS)}"
        )
    if lens_model == "pinhole":
        return cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    if lens_model == "opencv":
        return cv2.CALIB_FIX_K3
    # full_opencv: k1-k3 first, the rational terms after (`_free_rational`)
    return cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6


# the rational terms are kept only where they fit this much better than k1-k3 alone
RATIONAL_MIN_GAIN = 0.05


def _free_rational(obj, img, image_size, K, dist, rms, crit):
    """The rational model's k4-k6 freed from the k1-k3 fit (K, dist, rms): kept only when the
    RMS drops by `RATIONAL_MIN_GAIN` and the denominator 1 + k4 r^2 + k5 r^4 + k6 r^6 has no
    zero out to three times the image's corner radius. Freed from the start, calibrateCamera
    made numerator and denominator nearly cancel: a pole inside the image at 0.4 px RMS."""
    from calibration.checks import rational_pole

    w, h = image_size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_corner = float(np.max(np.linalg.norm((corners - K[:2, 2]) / np.diag(K)[:2], axis=1)))
    flags = cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_USE_INTRINSIC_GUESS
    rms2, K2, dist2, *_ = cv2.calibrateCameraExtended(
        obj, img, tuple(image_size), K.copy(), dist.copy(), flags=flags, criteria=crit
    )
    pole = rational_pole(dist2.ravel())
    ok = np.all(np.isfinite(dist2)) and (pole is None or pole > 3.0 * r_corner)
    if ok and rms2 < (1.0 - RATIONAL_MIN_GAIN) * rms:
        return K2, dist2, rms2
    return K, dist, rms


def spread_subset(items: list, n: int) -> list:
    """At most n items, evenly spaced through the list (keeps time diversity of board views)."""
    if len(items) <= n:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def calibrate_intrinsics(
    camera: str,
    detections: list[FrameDetection],
    board: BoardSpec,
    image_size: tuple[int, int],
    *,
    lens_model: str = "opencv",
    max_views: int = 40,
    outlier_factor: float = 3.0,
    min_outlier_px: float = 1.0,
    max_rounds: int = 3,
) -> Intrinsics:
    """cv2.calibrateCamera on up to `max_views` views spread through the footage.

    A view whose RMS exceeds max(`outlier_factor` x median view RMS, `min_outlier_px`) is
    rejected and the calibration repeated, up to `max_rounds` times.
    """
    min_views = 4
    if len(detections) < min_views:
        raise IntrinsicsError(
            f"camera '{camera}': only {len(detections)} board views, need at least "
            f"{min_views} to estimate intrinsics"
        )
    obj_all = board.object_points()
    views = spread_subset(sorted(detections, key=lambda d: d.frame), max_views)
    flags = _calib_flags(lens_model)
    rejected: list[int] = []
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    for k in range(max_rounds + 1):
        obj = [obj_all[d.ids].astype(np.float32) for d in views]
        img = [d.corners.astype(np.float32) for d in views]
        rms, K, dist, _, _, _, _, per_view = cv2.calibrateCameraExtended(
            obj, img, tuple(image_size), None, None, flags=flags, criteria=crit
        )
        if k == max_rounds:  # the solve without the last round's rejected views
            break
        per_view = per_view.ravel()
        limit = max(outlier_factor * float(np.median(per_view)), min_outlier_px)
        bad = per_view > limit
        if not bad.any() or len(views) - int(bad.sum()) < min_views:
            break
        rejected += [d.frame for d, b in zip(views, bad, strict=True) if b]
        views = [d for d, b in zip(views, bad, strict=True) if not b]
    if lens_model == "full_opencv":
        K, dist, rms = _free_rational(obj, img, image_size, K, dist, rms, crit)
    dist = dist.ravel().astype(np.float64)
    dist = dist[:8] if lens_model == "full_opencv" else np.concatenate([dist[:4], [0.0]])
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise IntrinsicsError(
            f"camera '{camera}': calibrateCamera returned an invalid K {K.tolist()}"
        )
    return Intrinsics(
        camera,
        K.astype(np.float64),
        dist,
        float(rms),
        sorted(d.frame for d in views),
        sorted(rejected),
    )


@dataclass(frozen=True)
class ViewPose:
    """Board pose in one camera view: X_cam = R X_board + t."""

    frame: int
    R: np.ndarray
    t: np.ndarray
    rms_px: float
    n_corners: int

    @property
    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


def board_pose(
    detection: FrameDetection,
    board: BoardSpec,
    K: np.ndarray,
    dist: np.ndarray,
    outlier_px: float = 3.0,
    min_corners: int = 4,
) -> ViewPose:
    """Board pose from one view: IPPE (both planar solutions, lowest error kept), then LM.

    Corners off by more than `outlier_px` are left out and the pose solved again (twice at
    most), so one bad corner does not spoil the view; `rms_px` is over the corners kept."""
    obj_all = board.object_points()[detection.ids]
    img_all = detection.corners
    keep = np.ones(len(obj_all), dtype=bool)
    for _ in range(3):
        obj, img = obj_all[keep], img_all[keep]
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if n == 0:
            raise IntrinsicsError(f"frame {detection.frame}: solvePnP found no board pose")
        best = int(np.argmin(np.asarray(errs).ravel()))
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(), tvecs[best].copy())
        proj, _ = cv2.projectPoints(obj_all, rvec, tvec, K, dist)
        err = np.linalg.norm(proj.reshape(-1, 2) - img_all, axis=1)
        new_keep = err <= outlier_px
        if new_keep.sum() < min_corners or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    rms = float(np.sqrt(np.mean(err[keep] ** 2)))
    return ViewPose(detection.frame, cv2.Rodrigues(rvec)[0], tvec.ravel(), rms, int(keep.sum()))
