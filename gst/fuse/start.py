"""Where the body fit starts: frames filled into short gaps, and a rigid start per frame.

- `dense_frames`: unseen frames inside gaps of at most `max_gap` frames are inserted (no
  evidence; the fit fills them from their neighbours);
- `rigid_start`: per frame, the rest-pose markers of the shoulders and hips are rigidly aligned
  (Kabsch) to their triangulated positions; a frame where nobody moved (every triangulated
  landmark within `tol` of the previous frame's) is flagged static and starts from the previous
  frame; a person never triangulated (seen by one camera at a time) starts upright, facing the
  camera, on the ray through the hips at the depth that makes the body 1.7 m tall.
"""

from __future__ import annotations

import numpy as np

from gst.fuse.observations import READABLE_CONFIDENCE, READABLE_LANDMARKS, PersonObservations
from gst.fuse.triangulate import PersonTriangulation

__all__ = ["TORSO_LANDMARKS", "dense_frames", "dense_triangulation", "nearest", "rigid_start"]

TORSO_LANDMARKS = (11, 12, 23, 24)  # shoulders and hips: the rigid start


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, c with dst ~ R src + c (rotation only), src/dst (n, 3)."""
    ms, md = src.mean(0), dst.mean(0)
    H = (src - ms).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return R, md - R @ ms


def _spread(frames: np.ndarray, dense: np.ndarray):
    """`take(a, fill)`: per-frame rows `a` (one per frame of sorted `frames`) laid out over the
    sorted superset `dense`, with `fill` in the frames `frames` lacks."""
    have = np.isin(dense, frames)
    src = np.where(have, np.searchsorted(frames, dense), 0)

    def take(a: np.ndarray, fill) -> np.ndarray:
        out = a[src].copy()
        out[~have] = fill
        return out

    return take


def nearest(good: np.ndarray, n: int) -> np.ndarray:
    """For each of the indices 0..n-1, the nearest of the sorted indices `good` (the first
    of two at the same distance)."""
    return good[np.abs(np.arange(n)[:, None] - good[None]).argmin(1)]


def dense_frames(obs: PersonObservations, max_gap: int) -> PersonObservations:
    """Insert unseen frames inside gaps of at most `max_gap` frames (filled by the fit)."""
    f = obs.frames
    if len(f) < 2:
        return obs
    full = np.concatenate(
        [f[:1]]
        + [
            np.arange(a + 1, b + 1) if b - a - 1 <= max_gap else np.array([b])
            for a, b in zip(f[:-1], f[1:], strict=True)
        ]
    )
    if len(full) == len(f):
        return obs
    take = _spread(f, full)
    return PersonObservations(
        obs.person_id,
        full,
        take(obs.uv, np.nan),
        take(obs.confidence, 0.0),
        take(obs.K, np.eye(3)),
        take(obs.Rt, np.eye(3, 4)),
        take(obs.px_scale, 1.0),
        take(obs.rows, -1),
    )


def rigid_start(
    obs: PersonObservations,
    tri: PersonTriangulation | None,
    rest_markers: np.ndarray,
    pelvis: np.ndarray,
    tol: float,
    up: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: root rotation (T, 3, 3), translation (T, 3) and the static flag (T,). `up`:
    the world's up direction (default +Z), for people no two cameras triangulate."""
    T = len(obs.frames)
    R = np.tile(np.eye(3), (T, 1, 1))
    c = np.full((T, 3), np.nan)
    static = np.zeros(T, bool)
    torso = list(TORSO_LANDMARKS)
    src = rest_markers[torso] - pelvis
    if tri is not None:
        for i in range(T):
            X = tri.points[i, torso]
            ok = np.isfinite(X).all(1)
            if ok.sum() >= 3:
                R[i], c[i] = _kabsch(src[ok], X[ok])
        pts = tri.points
        for i in range(1, T):
            both = np.isfinite(pts[i]).all(1) & np.isfinite(pts[i - 1]).all(1)
            if both.sum() >= 8 and np.abs(pts[i][both] - pts[i - 1][both]).max() < tol:
                static[i] = True
                R[i], c[i] = R[i - 1], c[i - 1]
    missing = ~np.isfinite(c).all(1)
    if missing.all():
        R, c = _single_view_start(obs, rest_markers, pelvis, up)
    elif missing.any():  # nearest frame with a start
        good = np.flatnonzero(~missing)
        near = nearest(good, T)
        R[missing], c[missing] = R[near[missing]], c[near[missing]]
    return R, c - pelvis[None], static


def _single_view_start(
    obs: PersonObservations,
    rest_markers: np.ndarray,
    pelvis: np.ndarray,
    up: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """No triangulation: upright along the world's `up` (default +Z), facing the camera, at the
    depth that makes the body 1.7 m."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    T = len(obs.frames)
    R = np.tile(np.eye(3), (T, 1, 1))
    c = np.zeros((T, 3))
    for i in range(T):
        # a landmark with NaN pixels is no reading, whatever its confidence
        read = (obs.confidence[i] > READABLE_CONFIDENCE) & np.isfinite(obs.uv[i]).all(-1)
        confident = read.sum(-1) * (obs.rows[i] >= 0)  # (C,)
        k = int(confident.argmax())  # the view that sees most of the body
        if confident[k] < READABLE_LANDMARKS:
            continue
        K, Rt = obs.K[i, k], obs.Rt[i, k]
        uv, w = obs.uv[i, k], read[k]
        height_px = np.ptp(uv[w, 1]) + 1e-6
        depth = K[1, 1] * 1.7 / height_px
        hips = uv[[23, 24]][np.isfinite(uv[[23, 24]]).all(-1)]
        # hips without pixels: the readable landmarks' centre (a NaN start in every frame left
        # nothing for `nearest` below, which failed with a bare argmin error)
        hips = hips.mean(0) if len(hips) else uv[w].mean(0)
        ray = np.linalg.solve(K, np.r_[hips, 1.0]) * depth  # camera frame
        Rc, tc = Rt[:, :3], Rt[:, 3]
        c[i] = Rc.T @ (ray - tc)
        # body axes in world: up = the world's, forward = towards the camera (horizontal)
        to_cam = -Rc.T @ tc - c[i]
        fwd = to_cam - (to_cam @ up) * up
        if np.linalg.norm(fwd) < 1e-6 * np.linalg.norm(to_cam):
            # straight below the camera: "towards it" has no horizontal part, and the zero
            # vector made no rotation; face the image's down direction instead
            down = Rc.T @ np.array([0.0, 1.0, 0.0])
            fwd = down - (down @ up) * up
        fwd /= np.linalg.norm(fwd) + 1e-9
        left = np.cross(up, fwd)
        R[i] = np.stack([left, up, fwd], 1)  # columns: model x, y, z in world
    seen = np.any(obs.rows >= 0, 1) & np.isfinite(c).all(1) & (np.abs(c).sum(1) > 0)
    good = np.flatnonzero(seen)
    if not len(good):
        raise ValueError(
            f"person {obs.person_id}: no view with at least {READABLE_LANDMARKS} landmarks above "
            f"confidence {READABLE_CONFIDENCE} that places a start (PersonObservations.readable "
            "is False, or the view's camera is not usable)"
        )
    near = nearest(good, T)
    return R[near], c[near]


def dense_triangulation(
    tri: PersonTriangulation, frames: np.ndarray, dense: np.ndarray
) -> PersonTriangulation:
    if len(frames) == len(dense):
        return tri
    take = _spread(frames, dense)
    return PersonTriangulation(
        take(tri.points, np.nan),
        take(tri.used, False),
        take(tri.errors, np.nan),
        take(tri.error, np.nan),
        take(tri.confidence, 0.0),
    )
