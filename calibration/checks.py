"""Plausibility checks of a rig against its capture volume (for imported calibrations too)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import Camera, Rig

# The widest barrel and the strongest pincushion a lens model may claim at the image's corners,
# as the undistorted (pinhole) radius over the distorted one: an action camera's wide lens is
# about 1.5, a telephoto's pincushion about 0.97. Beyond these a coefficient is in other units or
# on another parameter (k1 = 50 narrowed a 1920-px camera's field to a third of its pinhole one).
MAX_BARREL, MAX_PINCUSHION = 3.0, 0.6


@dataclass(frozen=True)
class CaptureVolume:
    """An axis-aligned box in world coordinates (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, dtype=float), np.asarray(self.hi, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or np.any(hi <= lo):
            raise ValueError(
                f"capture volume needs finite lo < hi 3-vectors, got {self.lo}, {self.hi}"
            )

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2

    def corners(self) -> np.ndarray:
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        return np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )

    def ray_hits(self, origin: np.ndarray, direction: np.ndarray) -> bool:
        """Whether the ray origin + s * direction (s >= 0) meets the box (slab test)."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        d = np.asarray(direction, dtype=float)
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to a slab: effectively infinite t
        t1, t2 = (lo - origin) / d, (hi - origin) / d
        near, far = np.max(np.minimum(t1, t2)), np.min(np.maximum(t1, t2))
        return bool(far >= max(near, 0.0))


def axes_meeting_point(rig: Rig) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis line."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in rig:
        d = cam.optical_axis
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ cam.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def estimate_volume(rig: Rig, height: float = 2.0) -> CaptureVolume:
    """A plausible capture volume for a z-up rig: centred under the point where the optical
    axes meet, from the floor (z = 0) to `height`, half as wide as the cameras are far from it."""
    up = np.asarray(rig.up)
    if not np.allclose(up, [0, 0, 1]):
        raise ValueError(f"estimate_volume needs a z-up rig, this one's up axis is {rig.up}")
    c = axes_meeting_point(rig)
    dist = (
        np.median([np.linalg.norm(cam.center[:2] - c[:2]) for cam in rig]) if len(rig) > 1 else 2.0
    )
    half = max(0.35 * dist, 0.5)
    return CaptureVolume((c[0] - half, c[1] - half, 0.0), (c[0] + half, c[1] + half, height))


def lens_problem(cam: Camera, samples: int = 64) -> str | None:
    """Why the camera's distortion cannot be a lens's (None when it can): within the image, a
    radial model must grow outward monotonically (no fold that sends two directions to one
    pixel), be invertible at the border (pixel -> ray -> the same pixel), and neither widen nor
    narrow the field beyond `MAX_BARREL` / `MAX_PINCUSHION` at the corners."""
    if not cam.dist.size or not np.any(cam.dist):
        return None
    w, h = float(cam.width), float(cam.height)
    border = (
        np.array([[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]])
        - 0.5
    )  # pixel-centre convention: the outer edge of the outer pixels
    rays = cam.undistort_points(border)
    t = np.linspace(1.0 / samples, 1.0, samples)
    along = (t[None, :, None] * rays[:, None, :]).reshape(-1, 2)  # (8 * samples, 2)
    pts = np.concatenate([along, np.ones((len(along), 1))], axis=1)
    zero, dist = np.zeros(3), cam.dist
    with np.errstate(all="ignore"):  # lens coordinates (no skew): radii from the centre
        uv = cv2.projectPoints(pts, zero, zero, cam.lens_K(), dist)[0].reshape(8, samples, 2)
    centre = np.array([cam.K[0, 2], cam.K[1, 2]])
    back = float(np.abs(cam.with_skew(uv[:, -1]) - border).max())
    if not np.isfinite(uv).all() or not back <= 1.0:
        return (
            f"camera '{cam.name}': its distortion {np.round(dist, 4).tolist()} cannot be "
            f"inverted at the image's border (a border pixel's ray projects {back:.1f} px away): "
            "the lens model folds inside the image"
        )
    radius = np.linalg.norm(uv - centre, axis=2)
    if np.any(np.diff(radius, axis=1) <= 0):
        return (
            f"camera '{cam.name}': its distortion {np.round(dist, 4).tolist()} folds inside the "
            "image (the distorted radius stops growing outward)"
        )
    corners = [0, 2, 4, 6]
    f = np.array([cam.K[0, 0], cam.K[1, 1]])
    r_d = np.linalg.norm((border[corners] - centre) / f, axis=1)
    r_u = np.linalg.norm(rays[corners], axis=1)
    ratio = float(np.median(r_u / np.maximum(r_d, 1e-12)))
    if not MAX_PINCUSHION <= ratio <= MAX_BARREL:
        return (
            f"camera '{cam.name}': its distortion {np.round(dist, 4).tolist()} makes the field "
            f"at the image's corners {ratio:.2f} x the pinhole one (a lens: "
            f"{MAX_PINCUSHION}-{MAX_BARREL}); are the coefficients in OpenCV's order and units?"
        )
    return None


def check_rig(rig: Rig, volume: CaptureVolume | None = None) -> list[str]:
    """Problems found (empty when plausible): lens models no lens has (`lens_problem`), cameras
    at or below the floor (z-up rigs) and cameras whose optical axis misses the capture
    volume."""
    problems = [p for p in (lens_problem(c) for c in rig) if p is not None]
    if np.allclose(rig.up, [0, 0, 1]):
        below = [f"{c.name} (z = {c.center[2]:.2f} m)" for c in rig if c.center[2] <= 0]
        if below:
            problems.append(f"cameras at or below the floor: {', '.join(below)}")
        volume = volume or estimate_volume(rig)
    if volume is not None:
        away = [c.name for c in rig if not volume.ray_hits(c.center, c.optical_axis)]
        if away:
            problems.append(
                f"optical axes miss the capture volume {volume.lo}..{volume.hi}: {away}"
            )
    return problems
