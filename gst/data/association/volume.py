"""The capture volume: a ground-aligned box over where the cameras look, and fast projection of
many points (voxel centres) through a camera's lens model."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration import Camera, Rig


@dataclass(frozen=True)
class CaptureVolume:
    """A box aligned with the ground: grid coordinates g = basis @ X_world, with basis rows
    (e1, e2, up); the box spans [lo, hi] in g."""

    basis: np.ndarray  # (3, 3)
    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)

    @staticmethod
    def ground_basis(up) -> np.ndarray:
        up = np.asarray(up, dtype=np.float64)
        up = up / np.linalg.norm(up)
        ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - up * (ref @ up)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        return np.stack([e1, e2, up])

    @classmethod
    def around(cls, center, half_extent, up=(0.0, 0.0, 1.0)) -> CaptureVolume:
        basis = cls.ground_basis(up)
        c = basis @ np.asarray(center, dtype=np.float64)
        h = np.broadcast_to(np.asarray(half_extent, dtype=np.float64), (3,))
        return cls(basis, c - h, c + h)

    @classmethod
    def from_rig(
        cls, rig: Rig, extent_factor: float = 0.8, half_height: float = 1.5
    ) -> CaptureVolume:
        """The region the cameras look at: a box around the point nearest to all optical axes,
        `extent_factor` times the median camera distance to it across the ground, and
        +-`half_height` metres along the up axis (cameras usually aim at people's middles)."""
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for cam in rig:
            d = cam.optical_axis
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ cam.center
        if np.linalg.cond(A) > 1e8:
            raise ValueError(
                f"cameras {rig.names} have parallel optical axes; "
                "give the capture volume explicitly"
            )
        center = np.linalg.solve(A, b)
        dist = np.median([np.linalg.norm(cam.center - center) for cam in rig])
        r = extent_factor * dist
        return cls.around(center, (r, r, half_height), rig.up)


def project_fast(cam: Camera, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project many points (float32 is fine) to distorted pixels; returns (uv, valid).

    The same model as `Camera.project` (`cv2.projectPoints`' radial k1..k6, tangential p1, p2,
    thin prism s1..s4, then the camera's skew, which OpenCV leaves out and H36M's cameras
    have), vectorised in numpy, which is several times faster
    for the millions of voxel centres of a grid. Tilted-sensor models (14 terms) go through
    OpenCV. Points behind the camera or outside the image's field of view (where the
    polynomial folds back) are marked invalid.
    """
    world = np.asarray(world)
    pc = world @ cam.R.T.astype(world.dtype) + cam.t.astype(world.dtype)
    z = pc[:, 2]
    valid = z > 1e-3
    zs = np.where(valid, z, 1.0)
    x, y = pc[:, 0] / zs, pc[:, 1] / zs
    lo, hi = _normalised_bounds(cam)
    valid &= (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
    d = np.zeros(12)
    d[: min(12, cam.dist.size)] = cam.dist[:12]
    if cam.dist.size == 14:
        uv = np.full((len(world), 2), -1e9)
        uv[valid] = cam.project(world[valid].astype(np.float64))
        return uv, valid
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    uv = np.stack([cam.fx * xd + cam.skew * yd + cam.cx, cam.fy * yd + cam.cy], axis=1)
    return uv, valid


def _normalised_bounds(cam: Camera, margin: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Box around the undistorted normalised coordinates of the image border, widened by
    `margin` of its size (a conservative pinhole stand-in for the lens model)."""
    w, h = cam.width, cam.height
    t = np.linspace(0, 1, 33)
    border = np.concatenate(
        [
            np.stack([t * (w - 1), np.zeros_like(t)], 1),
            np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
            np.stack([np.zeros_like(t), t * (h - 1)], 1),
            np.stack([np.full_like(t, w - 1), t * (h - 1)], 1),
        ]
    )
    xy = cam.undistort_points(border)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * (hi - lo)
    return lo - pad, hi + pad
