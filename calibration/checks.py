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


# A lens model that folds (its distorted radius stops growing) before this share of the way
# from the principal point to the image's border is no lens: refused (k1 = -5 on a lab camera:
# 26 %). One that folds nearer the border is a calibration poorly held there (a board never
# seen near the corners: tcrowd_dome_7010's board-solved 00_04, k2 = -0.56, folds 70 % of the
# way along its worst direction, 00_01 at 95 %): said, not refused.
FOLD_REFUSED = 0.5


def rational_pole(dist: np.ndarray) -> float | None:
    """The smallest normalised radius r > 0 where the rational model's denominator
    1 + k4 r^2 + k5 r^4 + k6 r^6 vanishes (OpenCV's 8+ terms: k4..k6 at 5..7), None if none."""
    dist = np.asarray(dist, np.float64).ravel()
    if dist.size < 8 or not np.any(dist[5:8]):
        return None
    k4, k5, k6 = dist[5:8]
    roots = np.roots([k6, k5, k4, 1.0])  # in s = r^2; np.roots drops leading zeros
    s = roots.real[(np.abs(roots.imag) < 1e-9 * np.maximum(1.0, np.abs(roots))) & (roots.real > 0)]
    return float(np.sqrt(s.min())) if s.size else None


def lens_findings(cam: Camera, samples: int = 256) -> tuple[str | None, str | None]:
    """(problem, warning) about the camera's distortion, None where there is none. Along the 8
    directions from the principal point to the image's corners and edge midpoints, the radial
    model is followed outward (rays of growing angle, projected with OpenCV) until its distorted
    radius stops growing: a lens's never does inside the image. A fold before `FOLD_REFUSED` of
    the way to the border is a problem, nearer the border a warning (points there are placed
    wrong). A model that reaches the border is a problem where it widens or narrows the field at
    the corners beyond `MAX_BARREL` / `MAX_PINCUSHION` of the pinhole one (k1 = 50: 0.32)."""
    if not cam.dist.size or not np.any(cam.dist):
        return None, None
    w, h = float(cam.width), float(cam.height)
    border = (
        np.array([[0, 0], [w / 2, 0], [w, 0], [w, h / 2], [w, h], [w / 2, h], [0, h], [0, h / 2]])
        - 0.5
    )  # pixel-centre convention: the outer edge of the outer pixels
    K = cam.lens_K()
    centre = K[:2, 2]
    f = np.array([K[0, 0], K[1, 1]])
    reach = np.linalg.norm(border - centre, axis=1)  # px to the border, per direction
    direction = (border - centre) / f
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    r_border = reach / f.mean()  # the border's normalised radius, near enough per direction
    pole = rational_pole(cam.dist)
    if pole is not None and pole < 3.0 * r_border.max():
        # 1 + k4 r^2 + k5 r^4 + k6 r^6 = 0: the model sends rays near that radius anywhere, in a
        # band thin enough to slip between the samples below (a rational fit whose numerator
        # and denominator nearly cancel: a low RMS, points in a ring thousands of px off)
        share = pole / r_border.max()
        return (
            f"camera '{cam.name}': its distortion {np.round(cam.dist, 4).tolist()} has a pole "
            f"(1 + k4 r^2 + k5 r^4 + k6 r^6 = 0) at {share:.0%} of the way to the image's "
            "border: no lens does; fit the rational terms only with views out to the corners, "
            "or use the 'opencv' lens model"
        ), None
    t = np.linspace(0.0, 1.0, samples + 1)[1:]
    r = t[None, :] * 3.0 * r_border[:, None]  # out to three times the pinhole border
    xy = direction[:, None, :] * r[..., None]  # (8, S, 2) undistorted, z = 1
    pts = np.concatenate([xy.reshape(-1, 2), np.ones((xy.size // 2, 1))], axis=1)
    zero, dist = np.zeros(3), cam.dist
    with np.errstate(all="ignore"):
        uv = cv2.projectPoints(pts, zero, zero, K, dist)[0].reshape(8, samples, 2)
    radius = np.where(np.isfinite(uv).all(-1), np.linalg.norm(uv - centre, axis=2), -np.inf)
    grows = np.diff(radius, axis=1, prepend=0.0) > 0
    stop = np.where(~grows.all(axis=1), np.argmin(grows, axis=1), samples)  # first non-growth
    reached = np.array(
        [radius[k, s - 1] if s > 0 else 0.0 for k, s in enumerate(stop)]
    )  # the largest radius the model reaches before it folds, px
    share = float(np.min(reached / reach))
    shown = np.round(dist, 4).tolist()
    if share < FOLD_REFUSED:
        return (
            f"camera '{cam.name}': its distortion {shown} folds {share:.0%} of the way to the "
            "image's border (its distorted radius stops growing): no lens does; are the "
            "coefficients in OpenCV's order and units?"
        ), None
    if share < 1.0:
        return None, (
            f"camera '{cam.name}': its distortion {shown} folds {share:.0%} of the way to the "
            "image's border: points near the corners are placed wrong (a calibration that never "
            "saw the board there?)"
        )
    corners = [0, 2, 4, 6]
    rays = cam.undistort_points(border[corners])
    r_d = np.linalg.norm((border[corners] - centre) / f, axis=1)
    ratio = float(np.median(np.linalg.norm(rays, axis=1) / np.maximum(r_d, 1e-12)))
    if not MAX_PINCUSHION <= ratio <= MAX_BARREL:
        return (
            f"camera '{cam.name}': its distortion {shown} makes the field at the image's corners "
            f"{ratio:.2f} x the pinhole one (a lens: {MAX_PINCUSHION}-{MAX_BARREL}); are the "
            "coefficients in OpenCV's order and units?"
        ), None
    return None, None


PRINCIPAL_POINT_OFF_CENTRE = 0.25  # share of the image's width / height


def lens_warnings(rig: Rig) -> list[str]:
    """What `lens_findings` says, but does not refuse, about the rig's cameras, and principal
    points further than PRINCIPAL_POINT_OFF_CENTRE of the image from its centre (a cropped
    video window can do that; so can a size edited for a rotated video, K left unturned)."""
    out = [w for w in (lens_findings(c)[1] for c in rig) if w is not None]
    for c in rig:
        off = (c.K[0, 2] / c.width - 0.5, c.K[1, 2] / c.height - 0.5)
        if max(abs(off[0]), abs(off[1])) > PRINCIPAL_POINT_OFF_CENTRE:
            out.append(
                f"camera '{c.name}': principal point ({c.K[0, 2]:.0f}, {c.K[1, 2]:.0f}) px lies "
                f"at {off[0] + 0.5:.0%} / {off[1] + 0.5:.0%} of its {c.width}x{c.height} image, "
                "far from the centre: check the image size and the video's orientation"
            )
    return out


def check_rig(rig: Rig, volume: CaptureVolume | None = None) -> list[str]:
    """Problems found (empty when plausible): lens models no lens has (`lens_findings`; what it
    only warns of is `lens_warnings`), cameras at or below the floor (z-up rigs) and cameras
    whose optical axis misses the capture volume."""
    problems = [p for p in (lens_findings(c)[0] for c in rig) if p is not None]
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
