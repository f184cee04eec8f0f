"""Triangulation of points seen by several cameras of a rig.

`triangulate_dlt` is the batched linear method (numpy, any number of points at once): pixels
are undistorted to normalised coordinates first, which keeps the DLT well conditioned, and each
point uses only the views that see it. `triangulate_robust` adds pycolmap's LO-RANSAC
estimator per point, for observations that may contain wrong views (e.g. a joint assigned to
the wrong person), with a nonlinear refinement of the inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Rig


@dataclass
class Triangulation:
    points: np.ndarray  # (N, 3) world points; NaN where fewer than 2 views saw the point, or
    # where the solution lies behind a view (then no view counts as used)
    errors_px: np.ndarray  # (C, N) reprojection error per view; NaN where unused
    used: np.ndarray  # (C, N) bool, views that took part (visible and, if robust, inliers)

    @property
    def n_views(self) -> np.ndarray:
        return self.used.sum(axis=0)


def _check(
    rig: Rig, pixels: np.ndarray, visible: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    pixels = np.asarray(pixels, dtype=np.float64)
    if pixels.ndim != 3 or pixels.shape[0] != len(rig) or pixels.shape[2] != 2:
        raise ValueError(f"pixels must have shape (cameras={len(rig)}, N, 2), got {pixels.shape}")
    vis = np.all(np.isfinite(pixels), axis=2)
    if visible is not None:
        visible = np.asarray(visible, dtype=bool)
        if visible.shape != pixels.shape[:2]:
            raise ValueError(f"visible must have shape {pixels.shape[:2]}, got {visible.shape}")
        vis &= visible
    return pixels, vis


def normalised_points(rig: Rig, pixels: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(C, N, 2) undistorted normalised coordinates (NaN where not visible)."""
    out = np.full(pixels.shape, np.nan)
    for c, cam in enumerate(rig):
        if visible[c].any():
            out[c, visible[c]] = cam.undistort_points(pixels[c, visible[c]])
    return out


def reprojection_errors(
    rig: Rig, points: np.ndarray, pixels: np.ndarray, used: np.ndarray
) -> np.ndarray:
    err = np.full(used.shape, np.nan)
    ok = np.all(np.isfinite(points), axis=1)
    for c, cam in enumerate(rig):
        m = used[c] & ok
        if m.any():
            err[c, m] = np.linalg.norm(cam.project(points[m]) - pixels[c, m], axis=1)
    return err


def dlt_points(P: np.ndarray, xy: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Linear (DLT) triangulation of N points seen by V views, all at once.

    P: (V, 3, 4) projection matrices; xy: (V, N, 2) image points in the same coordinates
    (pixels with P = K [R | t], normalised with P = [R | t]); weights: (V, N), 0 for an unseen
    view (NaN points count as unseen), e.g. detection confidences. Each view contributes the
    rows x P3 - P1 and y P3 - P2, scaled by its weight; one batched SVD solves them. Points seen
    with positive weight in fewer than 2 views are NaN. Returns (N, 3).
    """
    P = np.asarray(P, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64)
    w = np.ones(xy.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(np.isfinite(xy).all(axis=-1), np.nan_to_num(w), 0.0)
    x, y = np.nan_to_num(xy[..., 0]), np.nan_to_num(xy[..., 1])  # (V, N)
    rows_x = x[..., None] * P[:, None, 2, :] - P[:, None, 0, :]  # (V, N, 4)
    rows_y = y[..., None] * P[:, None, 2, :] - P[:, None, 1, :]
    # Rows interleaved per view (x, y of view 0, then view 1, ...), weighted.
    A = np.stack([rows_x, rows_y], axis=1) * w[:, None, :, None]  # (V, 2, N, 4)
    A = A.reshape(2 * P.shape[0], xy.shape[1], 4)  # (2V, N, 4); N may be 0 (an empty frame)
    if A.shape[1] == 0:
        return np.zeros((0, 3))
    _, _, Vt = np.linalg.svd(np.transpose(A, (1, 0, 2)))  # (N, 4, 4)
    Xh = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        points = Xh[:, :3] / Xh[:, 3:4]
    points[(w > 0).sum(axis=0) < 2] = np.nan
    return points


def triangulate_dlt(
    rig: Rig, pixels: np.ndarray, visible: np.ndarray | None = None
) -> Triangulation:
    """Linear triangulation of N points from (C, N, 2) pixels (NaN or `visible` False = unseen),
    in normalised coordinates (the lens model undone) with `dlt_points`."""
    pixels, vis = _check(rig, pixels, visible)
    xy = normalised_points(rig, pixels, vis)
    P = np.stack([np.hstack([c.R, c.t[:, None]]) for c in rig])  # (C, 3, 4)
    points = dlt_points(P, xy, vis.astype(np.float64))
    # A point behind a camera that sees it is no point (rays that diverge in front of the
    # cameras meet behind them); OpenCV's projection would fold it back onto its pixels, 0 px.
    depth = np.einsum("cj,nj->cn", P[:, 2, :3], np.nan_to_num(points)) + P[:, 2, 3][:, None]
    behind = (vis & ~(depth > 0)).any(0)
    points[behind] = np.nan
    vis = vis & ~behind[None]  # no view placed a point that is not there
    return Triangulation(points, reprojection_errors(rig, points, pixels, vis), vis)


def triangulate_robust(
    rig: Rig,
    pixels: np.ndarray,
    visible: np.ndarray | None = None,
    max_angle_error_deg: float = 1.0,
) -> Triangulation:
    """Per point, pycolmap's LO-RANSAC triangulation: views whose ray misses the point by more
    than `max_angle_error_deg` are outliers and left out. Slower than DLT (a Python loop)."""
    import pycolmap  # here, not at the top: the DLT path (training, fusion) needs no COLMAP

    pixels, vis = _check(rig, pixels, visible)
    # our lens model undone first (any distortion, skew), so COLMAP sees one identity pinhole:
    # its FULL_OPENCV has neither thin-prism terms nor skew (H36M's cameras have both)
    xy = normalised_points(rig, pixels, vis)
    unit = pycolmap.Camera(model="PINHOLE", width=2, height=2, params=[1.0, 1.0, 0.0, 0.0])
    poses = [pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t) for c in rig]
    opts = pycolmap.EstimateTriangulationOptions()
    opts.ransac.max_error = np.radians(max_angle_error_deg)
    opts.ransac.random_seed = 0
    n = pixels.shape[1]
    points = np.full((n, 3), np.nan)
    used = np.zeros_like(vis)
    for j in range(n):
        views = np.flatnonzero(vis[:, j])
        if len(views) < 2:
            continue
        res = pycolmap.estimate_triangulation(
            xy[views, j], [poses[v] for v in views], [unit] * len(views), opts
        )
        if res is None:
            continue
        points[j] = res["xyz"]
        used[views[np.asarray(res["inliers"], dtype=bool)], j] = True
    return Triangulation(points, reprojection_errors(rig, points, pixels, used), used)
