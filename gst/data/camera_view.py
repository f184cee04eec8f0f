"""The camera a video was filmed with, as tracking sees it.

Calibrated: the rig's `Camera`. Crops come from the undistorted image (same K), boxes found on
the raw frame are mapped into it, and results are also expressed in world coordinates.

Uncalibrated: a default pinhole camera from the frame size, camera-frame results only.
Default focal length f = sqrt(W^2 + H^2) px (the image diagonal; the convention CLIFF introduced
for in-the-wild images): a 53 degree diagonal field of view, 47 degrees across a 16:9 frame, the
same for portrait and landscape. It sits between a phone's main camera (about 65-75 degrees
horizontal) and a zoomed broadcast camera. A wrong focal length mostly rescales depth (and so
translation and world position), and changes the perspective the body is seen in: on the lab
capture (true focal 1680 px at 1088x1920, the default 2207) the network's projected joints lie
22.9 instead of 24.2 px from the landmark model's on cam01 with the true focal (docs/
track_evaluation.md, "The focal length of an uncalibrated video"). Where the focal length is
known (a phone's spec sheet gives it as a 35 mm equivalent), `focal_from_35mm` converts it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration import Camera
from calibration.camera import FRAME_PADDING_TOLERANCE, fit_to_frames
from gst.data.crop import CropWindow, crop_intrinsics, crop_window, cut_crop, cut_undistorted_crop

# diagonal of the 36 x 24 mm frame that "35 mm equivalent" focal lengths refer to
FILM_DIAGONAL_MM = float(np.hypot(36.0, 24.0))


def focal_from_35mm(focal_35mm: float, width: int, height: int) -> float:
    """Focal length in pixels of a `width` x `height` frame from its 35 mm equivalent (mm),
    the diagonals matched: the image diagonal (the default) is a 43.3 mm lens."""
    if not focal_35mm > 0:
        raise ValueError(f"35 mm equivalent focal length must be > 0 mm, got {focal_35mm}")
    return float(focal_35mm / FILM_DIAGONAL_MM * np.hypot(width, height))


def default_camera(
    width: int, height: int, name: str = "default", focal_px: float | None = None
) -> Camera:
    """Pinhole camera with focal `focal_px` (default: the image diagonal in px), principal point
    at the image centre, no distortion, identity pose (world = camera)."""
    f = float(np.hypot(width, height)) if focal_px is None else float(focal_px)
    if not f > 0:
        raise ValueError(f"focal length must be > 0 px, got {focal_px}")
    K = [[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    source = "image diagonal (px)" if focal_px is None else "given"
    return Camera.create(
        name,
        K,
        [],
        np.eye(3),
        np.zeros(3),
        width,
        height,
        meta={"source": f"default: focal = {source}, centred, no distortion"},
    )


def _box_outline(box: np.ndarray, per_edge: int = 8) -> np.ndarray:
    """Points along the edges of a corner-convention box, in pixel-centre coordinates."""
    x0, y0, x1, y1 = box - 0.5
    t = np.linspace(0.0, 1.0, per_edge)
    xs, ys = x0 + (x1 - x0) * t, y0 + (y1 - y0) * t
    return np.concatenate(
        [
            np.stack([xs, np.full_like(xs, y0)], 1),
            np.stack([xs, np.full_like(xs, y1)], 1),
            np.stack([np.full_like(ys, x0), ys], 1),
            np.stack([np.full_like(ys, x1), ys], 1),
        ]
    )


@dataclass(frozen=True)
class TrackingView:
    """Geometry of one video: crops, crop intrinsics, projection back to the raw frame, world."""

    camera: Camera
    calibrated: bool

    @classmethod
    def for_video(
        cls,
        width: int,
        height: int,
        camera: Camera | None = None,
        video: str = "video",
        tolerance: int = FRAME_PADDING_TOLERANCE,
        focal_px: float | None = None,
    ) -> TrackingView:
        """The calibrated `camera`, fitted to the frame size (encoder padding within
        `tolerance` pixels is accepted, `calibration.camera.fit_to_frames`), or the default
        camera (with `focal_px` when given)."""
        if camera is None:
            return cls(default_camera(width, height, focal_px=focal_px), calibrated=False)
        camera, _ = fit_to_frames(camera, width, height, tolerance, video)
        return cls(camera, calibrated=True)

    def to_json(self) -> dict:
        """The `gst.calibration` record of a tracks file (`from_json` reads it back)."""
        cam = self.camera
        return {
            "calibrated": self.calibrated,
            "name": cam.name,
            "width": cam.width,
            "height": cam.height,
            "K": cam.K.tolist(),
            "dist": cam.dist.tolist(),
            "R": cam.R.tolist(),
            "t": cam.t.tolist(),
            "meta": {k: str(v) for k, v in cam.meta.items()},
        }

    @classmethod
    def from_json(cls, record: dict) -> TrackingView:
        """The view a tracks file was made with, from its `gst.calibration` record (K, dist, R,
        t, width, height, calibrated; `to_json` writes it)."""
        camera = Camera.create(
            record.get("name", "default"),
            record["K"],
            record["dist"],
            record["R"],
            record["t"],
            record["width"],
            record["height"],
        )
        return cls(camera, calibrated=bool(record["calibrated"]))

    @property
    def has_distortion(self) -> bool:
        return bool(self.camera.dist.size and np.any(self.camera.dist))

    def model_box(self, box_raw: np.ndarray) -> np.ndarray:
        """A detection box on the raw frame -> the box enclosing it in the undistorted image."""
        box_raw = np.asarray(box_raw, dtype=np.float64)
        if not self.has_distortion:
            return box_raw
        xy = self.camera.undistort_points(_box_outline(box_raw))
        uv = xy @ self.camera.K[:2, :2].T + self.camera.K[:2, 2]
        lo, hi = uv.min(0), uv.max(0)
        return np.concatenate([lo, hi]) + 0.5  # back to the corner convention

    def window(self, box_raw: np.ndarray, size: int) -> CropWindow:
        return crop_window(self.model_box(box_raw), size)

    def crop(self, frame: np.ndarray, window: CropWindow) -> tuple[np.ndarray, np.ndarray]:
        """(crop in the frame's channel order, K_crop)."""
        if self.has_distortion:
            img = cut_undistorted_crop(frame, self.camera, window)
        else:
            img = cut_crop(frame, window)
        return img, crop_intrinsics(self.camera.K, window)

    def to_world(self, points_cam: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame points -> world (only meaningful when calibrated)."""
        p = np.asarray(points_cam, dtype=np.float64)
        return (p - self.camera.t) @ self.camera.R

    def rotation_to_world(self, rotmats_cam: np.ndarray) -> np.ndarray:
        """(..., 3, 3) camera-frame orientations -> world: R^T @ rot."""
        return np.einsum(
            "ji,...jk->...ik", self.camera.R, np.asarray(rotmats_cam, dtype=np.float64)
        )

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, J, 3) camera-frame points -> (N, J, 2) raw-frame pixels (pixel-centre convention),
        through the lens distortion when there is one."""
        p = np.asarray(points_cam, dtype=np.float64)
        flat = p.reshape(-1, 3)
        if self.has_distortion:
            uv = self.camera.project(self.to_world(flat))
        else:
            z = flat[:, 2:3]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = (flat[:, :2] / z) @ self.camera.K[:2, :2].T + self.camera.K[:2, 2]
        return uv.reshape(p.shape[:-1] + (2,))
