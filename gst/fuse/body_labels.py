"""Who is where in one camera's image, from the fitted bodies (docs/fuse.md "Crops from the
fitted bodies").

A ray through each pixel meets the nearest body mesh (Embree, `synth.render.RayCaster`); that
body owns the pixel. The image's foreground then decides what is person at all: a foreground
pixel goes to the body that owns it, or else to the body owning the nearest owned pixel within
`max_distance_px` (a silhouette edge, a body fitted a little off); foreground further from every
body is nobody's, and so is a body's pixel outside the foreground. Only the pixels that can
decide a label are cast: those within `max_distance_px` of the foreground, inside the bodies'
projected boxes.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

from calibration.camera import Camera
from synth.render import RayCaster

__all__ = ["CameraRays", "body_labels"]

NOBODY = -1
BOX_STRIDE = 4  # every 4th vertex of a dense mesh bounds its box well within the margin


class CameraRays:
    """The viewing rays of a camera's pixels at a working size (`size` = width, height, a
    scaling of the camera's image): world unit directions `dirs` (h, w, 3) through the pixel
    centres, through the lens model, and their undistorted normalised coordinates `xy`."""

    def __init__(self, camera: Camera, size: tuple[int, int]):
        w, h = size
        self.camera, self.width, self.height = camera, w, h
        self.scale = (w / camera.width, h / camera.height)
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        full = np.stack([(uu + 0.5) / self.scale[0] - 0.5, (vv + 0.5) / self.scale[1] - 0.5], -1)
        xy = camera.undistort_points(full.reshape(-1, 2))
        self.xy = xy.astype(np.float32).reshape(h, w, 2)  # undistorted normalised coordinates
        d = np.c_[xy, np.ones(len(xy))] @ camera.R  # R^T (x, y, 1): camera to world
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        self.dirs = d.astype(np.float32).reshape(h, w, 3)
        self.origin = camera.center.astype(np.float32)

    def box(self, vertices: np.ndarray, margin: float) -> tuple[int, int, int, int] | None:
        """Pixel box x0, y0, x1, y1 (exclusive ends) at the working size around the projection
        of `vertices` (N, 3) in front of the camera, grown by `margin` pixels and clipped to the
        image; None when nothing of them is in front of the camera or in the image."""
        if len(vertices) > 1000:
            vertices = vertices[::BOX_STRIDE]
        front = self.camera.to_camera(vertices)[:, 2] > 1e-3
        if not front.any():
            return None
        uv = self.camera.project(vertices[front])
        uv = (uv + 0.5) * np.asarray(self.scale) - 0.5
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if not len(uv):
            return None
        x0, y0 = np.floor(uv.min(0) - margin).astype(int)
        x1, y1 = np.ceil(uv.max(0) + margin).astype(int) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.width), min(y1, self.height)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def body_labels(
    rays: CameraRays,
    meshes: list[np.ndarray],
    caster: RayCaster,
    foreground: np.ndarray,
    max_distance_px: float = 8.0,
) -> np.ndarray:
    """(h, w) int16 image at the rays' working size: the index into `meshes` ((V, 3) world
    vertices each) of the body each foreground pixel belongs to, -1 for nobody. `caster` holds
    the same meshes in the same order (built once per frame, shared by the cameras);
    `foreground` is (h, w) bool."""
    h, w = rays.height, rays.width
    if foreground.shape != (h, w):
        raise ValueError(f"foreground is {foreground.shape}, the rays are {h}x{w}")
    labels = np.full((h, w), NOBODY, np.int16)
    margin = max_distance_px + 1
    boxes = [rays.box(v, margin) for v in meshes]
    seen = [k for k, b in enumerate(boxes) if b is not None]
    if len(meshes) != len(caster.meshes):
        raise ValueError(f"{len(meshes)} meshes, the caster holds {len(caster.meshes)}")
    if not seen:
        return labels
    x0 = min(boxes[k][0] for k in seen)
    y0 = min(boxes[k][1] for k in seen)
    x1 = max(boxes[k][2] for k in seen)
    y1 = max(boxes[k][3] for k in seen)
    fg = foreground[y0:y1, x0:x1].astype(bool)
    # a foreground pixel's label comes from an owned pixel at most max_distance_px away, so
    # pixels farther than that from all foreground need no ray (the labels do not change)
    near_fg = cv2.dilate(fg.view(np.uint8), disk(max_distance_px)) > 0
    owner = np.full(fg.shape, NOBODY, np.int16)
    if near_fg.any():
        hits = caster.cast(rays.origin[None], rays.dirs[y0:y1, x0:x1][near_fg])
        owner[near_fg] = hits.geom
    if not (owner >= 0).any():
        return labels
    distance, (iy, ix) = distance_transform_edt(owner < 0, return_indices=True)
    near = owner[iy, ix]
    labels[y0:y1, x0:x1] = np.where(fg & (distance <= max_distance_px), near, NOBODY)
    return labels


def disk(radius: float) -> np.ndarray:
    """uint8 structuring element of every pixel offset within `radius` (Euclidean)."""
    r = int(np.floor(radius))
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    return (dx * dx + dy * dy <= radius * radius).astype(np.uint8)
