"""Pinhole cameras with OpenCV distortion, and rigs of them.

Conventions (used everywhere in this project):
- World units are metres. Extrinsics map world to camera: X_cam = R @ X_world + t.
- Camera axes follow OpenCV: x right, y down, z forward (into the scene).
- Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0), so pixel (u, v)
  covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5].
- Distortion coefficients are OpenCV's order:
  k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]].
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Protocol

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger("calibration")

_VALID_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
# How far outside the image (a share of its width and height) a point may lie for the lens model
# to place it (Camera.in_field): beyond that a distortion polynomial is extrapolated and can put
# a point anywhere (a wrong skeleton's limb beside a camera landed millions of pixels away, and
# its view's crop with it: docs/extract.md "Points beside a camera").
FIELD_MARGIN = 0.5
# an undistorted point must project back this close (px) to its pixel (`exact_only`)
ROUND_TRIP_PX = 0.5


def is_pixel_count(value) -> bool:
    """Whether `value` is an image side in pixels: a whole number (1920 or 1920.0), never a
    bool, text or 1000.9."""
    number = isinstance(value, (int, float, np.integer, np.floating))
    return number and not isinstance(value, (bool, np.bool_)) and float(value).is_integer()


class CameraError(ValueError):
    """A camera or rig is malformed; the message names the camera and the field."""


def _as_array(value, shape: tuple[int, ...], what: str, camera: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"camera '{camera}': {what} is not numeric ({exc})") from exc
    if arr.size == int(np.prod(shape)) and arr.shape != shape:
        arr = arr.reshape(shape)
    if arr.shape != shape:
        raise CameraError(f"camera '{camera}': {what} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise CameraError(f"camera '{camera}': {what} contains NaN or Inf: {arr.tolist()}")
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera. Build it with `Camera.create(...)`, which validates every field."""

    name: str
    K: np.ndarray  # (3, 3) intrinsics: [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]
    dist: np.ndarray  # (N,) OpenCV distortion, N in {0, 4, 5, 8, 12, 14}
    R: np.ndarray  # (3, 3) world-to-camera rotation
    t: np.ndarray  # (3,) world-to-camera translation, metres
    width: int
    height: int
    meta: dict = field(default_factory=dict)  # free-form provenance (source format, serial...)

    @classmethod
    def create(cls, name, K, dist, R, t, width, height, meta=None, orthonormal_tol=1e-6) -> Camera:
        name = str(name)
        K = _as_array(K, (3, 3), "K", name)
        dist = np.asarray(dist if dist is not None else [], dtype=np.float64).ravel()
        if dist.size not in _VALID_DIST_LENGTHS:
            raise CameraError(
                f"camera '{name}': distortion has {dist.size} terms, expected one of "
                f"{_VALID_DIST_LENGTHS} (OpenCV order k1, k2, p1, p2, k3, ...)"
            )
        if not np.all(np.isfinite(dist)):
            raise CameraError(f"camera '{name}': distortion contains NaN or Inf: {dist.tolist()}")
        R = _as_array(R, (3, 3), "R", name)
        t = _as_array(t, (3,), "t", name)
        ortho_err = float(np.abs(R @ R.T - np.eye(3)).max())
        if ortho_err > orthonormal_tol:
            raise CameraError(
                f"camera '{name}': R is not orthonormal (max |R R^T - I| = {ortho_err:.2e}, "
                f"tolerance {orthonormal_tol:.0e})"
            )
        if np.linalg.det(R) < 0:
            raise CameraError(f"camera '{name}': R is a reflection (det = -1), expected a rotation")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(
                f"camera '{name}': focal lengths must be positive, got K = {K.tolist()}"
            )
        if (
            abs(K[2, 2] - 1) > 1e-9
            or abs(K[1, 0]) > 1e-9
            or abs(K[2, 0]) > 1e-9
            or abs(K[2, 1]) > 1e-9
        ):
            raise CameraError(
                f"camera '{name}': K must be upper triangular with K[2,2] = 1, got {K.tolist()}"
            )
        for side, value in (("width", width), ("height", height)):
            # int() took 1920.7 as 1920 and True as 1: a camera of another size, silently
            if not is_pixel_count(value):
                raise CameraError(
                    f"camera '{name}': {side} is {value!r}, expected a whole number of pixels"
                )
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise CameraError(f"camera '{name}': resolution must be positive, got {width}x{height}")
        return cls(name, K, dist, R, t, width, height, dict(meta or {}))

    # -- derived quantities -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def skew(self) -> float:
        return float(self.K[0, 1])

    def lens_K(self) -> np.ndarray:
        """K without the skew: what OpenCV's lens functions read (they ignore K[0, 1]); pixels
        they give go through `with_skew`."""
        K = self.K.copy()
        K[0, 1] = 0.0
        return K

    def with_skew(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) computed with `lens_K`, with the camera's skew: u += skew (v - cy) / fy
        (a copy; `uv` itself where the camera has none)."""
        if not self.skew:
            return uv
        uv = np.array(uv, dtype=np.float64)
        uv[..., 0] += self.skew * (uv[..., 1] - self.cy) / self.fy
        return uv

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def optical_axis(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    @property
    def world_to_cam(self) -> np.ndarray:
        """4x4 world-to-camera matrix (a 'viewmat' in splatting terms)."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    @property
    def rvec(self) -> np.ndarray:
        """Rotation vector (axis times angle, radians) of R, as OpenCV's Rodrigues convention.

        Not cv2.Rodrigues: it returns a zero vector for rotations below ~1e-5 rad, so files that
        store rvecs (Anipose, Pose2Sim) lost such rotations. scipy's conversion is exact there.
        """
        return Rotation.from_matrix(self.R).as_rotvec()

    def replace(self, **changes) -> Camera:
        """A validated copy with some fields changed."""
        current = {f.name: getattr(self, f.name) for f in fields(self)}
        return Camera.create(**{**current, **changes})

    # -- geometry through OpenCV --------------------------------------------------------------
    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return pts @ self.R.T + self.t

    def in_field(
        self, points_world: np.ndarray, margin: float = FIELD_MARGIN, min_depth: float = 1e-3
    ) -> np.ndarray:
        """(N,) bool: the points at least `min_depth` in front of the camera whose pinhole
        projection lies within `margin` x the image's width and height of the image. Beyond
        that the lens model is extrapolated: a distortion polynomial evaluated far outside the
        field it was calibrated on can put a point anywhere, even back inside the image."""
        xyz = self.to_camera(points_world)
        z = xyz[:, 2]
        front = np.isfinite(xyz).all(axis=1) & (z > min_depth)
        with np.errstate(divide="ignore", invalid="ignore"):
            pin = (xyz[:, :2] / z[:, None]) @ self.K[:2, :2].T + self.K[:2, 2]
        size = np.array([self.width, self.height], np.float64)
        return front & np.all((pin > -margin * size) & (pin < (1 + margin) * size), axis=1)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Project (N, 3) world points to (N, 2) distorted pixels with cv2.projectPoints.

        Points behind the camera or far outside its field are projected too (OpenCV does not
        clip); check them with `in_field` when it matters.
        """
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return np.zeros((0, 2))
        # Points go to the camera frame here, not through an rvec: cv2.Rodrigues treats
        # rotations below ~1e-5 rad as the identity.
        return self._lens_project(self.to_camera(pts))

    def _lens_project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points to (N, 2) distorted pixels. cv2.projectPoints ignores
        K[0, 1] (skew): project without it and add it after."""
        zero = np.zeros(3)
        uv, _ = cv2.projectPoints(
            points_cam, zero, zero, self.lens_K(), self.dist if self.dist.size else None
        )
        return self.with_skew(uv.reshape(-1, 2))

    def undistort_points(self, pixels: np.ndarray, exact_only: bool = False) -> np.ndarray:
        """Distorted pixels (N, 2) to undistorted normalised coordinates (N, 2) (z = 1 plane).

        `exact_only`: NaN for pixels whose undistorted point does not project back onto them
        (within ROUND_TRIP_PX): beyond the radius where a barrel lens model stops being
        invertible (a landmark the person model placed outside the frame, for a limb cut off
        by its edge) the iteration returns a point hundreds of pixels from the true ray."""
        px = np.array(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(px) == 0:
            return np.zeros((0, 2))
        if exact_only and self.dist.size and np.any(self.dist):
            xy = self.undistort_points(px.reshape(-1, 2))
            back = self.project_normalised(xy)
            far = ~(np.linalg.norm(back - px.reshape(-1, 2), axis=1) <= ROUND_TRIP_PX)
            xy[far] = np.nan
            return xy
        if self.skew:  # cv2.undistortPoints ignores skew too: remove it first
            px[:, 0, 0] -= self.skew * (px[:, 0, 1] - self.cy) / self.fy
        # wide strong lenses need hundreds of iterations (50 left 0.6 px at 90-120 degrees);
        # the usual ones stop at the 1e-12 step after a few
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 2000, 1e-12)
        dist = self.dist if self.dist.size else None
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4 (5 folded it into undistortPoints)
            out = cv2.undistortPointsIter(px, self.lens_K(), dist, None, None, crit)
        else:
            out = cv2.undistortPoints(px, self.lens_K(), dist, None, None, None, crit)
        return out.reshape(-1, 2)

    def project_normalised(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) (z = 1 plane) to distorted pixels (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(xy) == 0:
            return np.zeros((0, 2))
        return self._lens_project(np.c_[xy, np.ones(len(xy))])

    def unproject(
        self, pixels: np.ndarray, depth: np.ndarray | float | None = None, exact_only: bool = False
    ) -> np.ndarray:
        """Pixels to world. With `depth` (camera z, metres) returns (N, 3) points; without it,
        returns (N, 3) unit ray directions in world coordinates. `exact_only`: NaN for pixels
        beyond where the lens model inverts (`undistort_points`)."""
        xy = self.undistort_points(pixels, exact_only=exact_only)
        rays_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        if depth is None:
            d = rays_cam @ self.R  # R^T applied to row vectors
            return d / np.linalg.norm(d, axis=1, keepdims=True)
        pts_cam = rays_cam * np.asarray(depth, dtype=np.float64).reshape(-1, 1)
        return (pts_cam - self.t) @ self.R

    def undistort_image(self, image: np.ndarray) -> np.ndarray:
        """Remove lens distortion from an image (same K)."""
        if not self.dist.size or not np.any(self.dist):
            return image
        if self.skew:
            raise CameraError(
                f"camera '{self.name}': undistort_image does not support skew "
                "(OpenCV ignores K[0, 1])"
            )
        return cv2.undistort(image, self.K, self.dist)


FRAME_PADDING_TOLERANCE = 16  # pixels; H.264 pads frame sizes to multiples of 16


def fit_to_frames(
    camera: Camera, width: int, height: int, tolerance: int = FRAME_PADDING_TOLERANCE, source=""
) -> tuple[Camera, str | None]:
    """The camera for decoded frames of `width` x `height`, and a note when they differ.

    Encoders pad a frame to a multiple of 16 (1080 rows become 1088), and a calibration can
    state the padded size while the video decodes to the real one, or the other way round. The
    padding sits at the bottom and the right, so the intrinsics hold as they are: frames that
    are smaller than the calibrated size by at most `tolerance` pixels in each direction give
    the same camera with the frame size. Anything else (larger frames, a bigger difference, a
    rotated frame) raises CameraError naming the camera, both sizes and the fix."""
    if (width, height) == (camera.width, camera.height):
        return camera, None
    dw, dh = camera.width - width, camera.height - height
    if 0 <= dw <= tolerance and 0 <= dh <= tolerance:
        note = (
            f"camera '{camera.name}': frames are {width}x{height}, the calibration says "
            f"{camera.width}x{camera.height} (encoder padding of {dw} columns and {dh} rows at "
            "the right and bottom); using the calibration's intrinsics with the frame size"
        )
        resized = Camera(
            camera.name, camera.K, camera.dist, camera.R, camera.t, width, height,
            {**camera.meta, "frame_size_note": note},
        )  # fmt: skip
        return resized, note
    where = f" ({source})" if source else ""
    if (width, height) == (camera.height, camera.width):
        # swapping the size in the file would not turn K and R: the "fixed" rig passed every
        # check with its principal point far off the image's centre
        raise CameraError(
            f"camera '{camera.name}'{where}: frames are {width}x{height}, the calibration's "
            f"{camera.width}x{camera.height} turned by 90 degrees: the video is rotated against "
            "the calibration (a phone's or an exporter's rotation). Turn the video back to the "
            "orientation it was calibrated in (e.g. ffmpeg -vf transpose=1 or 2), or "
            "calibrate the turned video; editing the size in the calibration is not enough "
            "(K and R would stay the unturned camera's)"
        )
    raise CameraError(
        f"camera '{camera.name}'{where}: frames are {width}x{height}, but the calibration says "
        f"{camera.width}x{camera.height}; frames up to {tolerance} px smaller (encoder padding) "
        "are accepted. Fix the camera's image size in the calibration file (rig.json "
        "width/height; Qualisys fov_video; Panoptic resolution), or, if the difference is "
        "padding, raise the scene's frame_size_tolerance, e.g. "
        "--set scenes.NAME.frame_size_tolerance=32"
    )


@dataclass(frozen=True, eq=False)
class RigArrays:
    """A rig's cameras as arrays stacked in rig order (`Rig.stacked`): K (C, 3, 3), R (C, 3, 3),
    t (C, 3), dist (C, D) zero-padded to the longest model, size (C, 2) as (width, height)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray
    size: np.ndarray


@dataclass(frozen=True, eq=False)
class Rig:
    """An ordered set of cameras sharing one world frame (metres, `up` is the world up axis)."""

    cameras: tuple[Camera, ...]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    units: str = "m"
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "cameras", tuple(self.cameras))
        names = [c.name for c in self.cameras]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CameraError(f"rig has duplicate camera names: {dupes}")
        if self.units != "m":
            raise CameraError(
                f"rig units must be metres ('m'), got '{self.units}'; convert on import"
            )
        up = np.asarray(self.up, dtype=np.float64)
        if up.shape != (3,) or not np.all(np.isfinite(up)) or abs(np.linalg.norm(up) - 1) > 1e-6:
            raise CameraError(f"rig up axis must be a finite unit 3-vector, got {self.up}")

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for cam in self.cameras:
                if cam.name == key:
                    return cam
            raise KeyError(f"camera '{key}' is not in the rig (cameras: {self.names})")
        return self.cameras[key]

    def subset(self, names: list[str]) -> Rig:
        return replace(self, cameras=tuple(self[n] for n in names))

    def transformed(
        self,
        rotation: np.ndarray,
        translation: np.ndarray,
        scale: float = 1.0,
        up: tuple[float, float, float] | None = None,
    ) -> Rig:
        """The same cameras in a new world frame, X_new = scale * rotation @ X_old + translation.

        `up` is the new world's up axis; by default the old one carried over by `rotation`.
        """
        Rw = _as_array(rotation, (3, 3), "rotation", "<rig transform>")
        tw = _as_array(translation, (3,), "translation", "<rig transform>")
        if not (np.isfinite(scale) and scale > 0):
            raise CameraError(f"rig transform scale must be positive, got {scale}")
        cams = tuple(c.replace(R=c.R @ Rw.T, t=scale * c.t - c.R @ Rw.T @ tw) for c in self.cameras)
        new_up = np.asarray(up if up is not None else Rw @ np.asarray(self.up), dtype=np.float64)
        return replace(
            self, cameras=cams, up=tuple(float(v) for v in new_up / np.linalg.norm(new_up))
        )

    def stacked(self) -> RigArrays:
        """Per-camera arrays stacked in rig order, for batched code (`RigArrays`)."""
        n_dist = max([5] + [c.dist.size for c in self.cameras])
        dist = np.zeros((len(self.cameras), n_dist))
        for i, c in enumerate(self.cameras):
            dist[i, : c.dist.size] = c.dist
        return RigArrays(
            K=np.stack([c.K for c in self.cameras]),
            R=np.stack([c.R for c in self.cameras]),
            t=np.stack([c.t for c in self.cameras]),
            dist=dist,
            size=np.array([[c.width, c.height] for c in self.cameras]),
        )


def look_at_rotation(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera rotation of an OpenCV camera at `position` looking at `target`, with the
    image's up direction (-y) as close to the world `up` as possible."""
    position, target, up = (np.asarray(v, dtype=np.float64) for v in (position, target, up))
    z = target - position
    if np.linalg.norm(z) < 1e-12:
        raise CameraError("look_at: position and target coincide")
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise CameraError("look_at: viewing direction is parallel to the up vector")
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def project_points_torch(points, K, R, t, dist=None):
    """Differentiable batched projection with OpenCV's distortion model, in torch.

    points (..., N, 3) world points; K (..., 3, 3) (skew honoured); R (..., 3, 3) and t (..., 3)
    world-to-camera; dist (..., D) with D in {0, 4, 5, 8, 12}: k1, k2, p1, p2[, k3[, k4, k5,
    k6[, s1..s4]]] (the tilted model, D = 14, is not supported). Batch dimensions broadcast.
    Returns (..., N, 2) pixels. Points at or behind the camera give non-finite or meaningless
    pixels, as in OpenCV; mask them by depth (`(points @ R^T + t)[..., 2] > 0`) where it matters.
    """
    import torch

    X = points @ R.transpose(-1, -2) + t.unsqueeze(-2)
    x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    if dist is not None and dist.shape[-1] > 0:
        D = dist.shape[-1]
        if D not in (4, 5, 8, 12):
            raise CameraError(
                f"project_points_torch: {D} distortion terms, expected 0, 4, 5, 8 or 12"
            )
        d = dist.unsqueeze(-2)  # broadcast against N

        def term(i):
            return d[..., i] if i < D else torch.zeros((), dtype=x.dtype, device=x.device)

        r2 = x * x + y * y
        r4, r6 = r2 * r2, r2 * r2 * r2
        radial = (1 + term(0) * r2 + term(1) * r4 + term(4) * r6) / (
            1 + term(5) * r2 + term(6) * r4 + term(7) * r6
        )
        p1, p2 = term(2), term(3)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + term(8) * r2 + term(9) * r4
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + term(10) * r2 + term(11) * r4
        x, y = xd, yd
    Kb = K.unsqueeze(-3)
    u = Kb[..., 0, 0] * x + Kb[..., 0, 1] * y + Kb[..., 0, 2]
    v = Kb[..., 1, 1] * y + Kb[..., 1, 2]
    return torch.stack([u, v], dim=-1)


class FrameSize(Protocol):
    """What `fit_rig_to_frames` reads of a video (gst.video.VideoInfo has it)."""

    width: int
    height: int
    path: object


def fit_rig_to_frames(
    rig: Rig, frames: Mapping[str, FrameSize], tolerance: int = FRAME_PADDING_TOLERANCE
) -> tuple[Rig, list[str]]:
    """The rig with every camera named in `frames` fitted to its video's decoded frame size
    (`fit_to_frames`: padding within `tolerance` px accepted, noted and logged; anything else
    raises CameraError with the fix), and the notes. Other cameras stay as they are."""
    cams, notes = [], []
    for cam in rig:
        if cam.name in frames:
            f = frames[cam.name]
            cam, note = fit_to_frames(cam, f.width, f.height, tolerance, str(f.path))
            if note:
                log.warning("%s", note)
                notes.append(note)
        cams.append(cam)
    return Rig(tuple(cams), rig.up, rig.units, rig.meta), notes
