"""Place the network's body on the landmark model's 2D joints by moving it, never reshaping it.

A single-image network reads a person's depth and position from the crop's extent and its own
impression of the body, so its projected joints sit beside the person on footage unlike its
training crops (the lab capture with the demo's model: the pelvis ~50 px off at 1088x1920). The
landmark model's 2D joints are sharper evidence for *where* the body is. `align_translation`
solves for the one camera-frame shift of each body parallel to the image plane, at the network's
depth (pose, shape and joint layout untouched), that brings its joints closest to the confident
landmarks of the same joints (the 13 pairs of gst.track.agreement): robust (Huber) reprojection
in crop pixels, Gauss-Newton. Depth stays the network's: fitting it to the 2D scale as well
made the demo's root error worse (mean over the 6 cameras 126 mm, against 120 mm unaligned and
115 mm with the lateral shift alone), since a wrong limb pose also changes the 2D extent. Bodies
with fewer than `min_joints` confident landmarks keep their place.

`joints2d` then differs from the landmarks by the body's pose and shape only
(`joints2d_vs_landmarks` in the track summary). `track.align_to_landmarks: false` keeps the
network's own translation (benchmarks/bench_track.py --real measures both).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gst.track.agreement import COMPARED_INDEX, landmark_targets


@dataclass(frozen=True)
class AlignmentConfig:
    min_confidence: float = 0.5  # landmarks below this are no evidence
    min_joints: int = 4  # fewer confident joints: the body keeps the network's place
    huber_fraction: float = 0.05  # Huber scale: this share of the landmarks' extent (px)
    iterations: int = 8


def align_translation(
    joints_cam: np.ndarray,
    K_crop: np.ndarray,
    landmarks_crop: np.ndarray,
    config: AlignmentConfig = AlignmentConfig(),
) -> np.ndarray:
    """(B, 3) camera-frame shifts (z = 0) that put each body (B, 24, 3 camera-frame joints) on
    the crop's landmarks (B, 33, 3: u, v crop px + confidence, NaN rows where none); zero where
    there is too little evidence or the solve is not sane."""
    X0 = np.asarray(joints_cam, np.float64)[:, COMPARED_INDEX]  # (B, 13, 3)
    K = np.asarray(K_crop, np.float64)
    target, w = landmark_targets(landmarks_crop, config.min_confidence)
    B = len(X0)
    t = np.zeros((B, 3))
    usable = ((w > 0).sum(1) >= config.min_joints) & (X0[..., 2] > 0.05).all(1)
    if not usable.any():
        return t
    X0, K, target, w = X0[usable], K[usable], target[usable], w[usable]
    sure = np.where(w[..., None] > 0, target, np.nan)  # (b, 13, 2), >= min_joints finite
    extent = (np.nanmax(sure, axis=1) - np.nanmin(sure, axis=1)).max(axis=1)
    delta = np.maximum(config.huber_fraction * extent, 2.0)[:, None]  # (b, 1) px
    fx, fy, cx, cy = K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 2, None], K[:, 1, 2, None]
    tb = np.zeros((len(X0), 3))
    # each body stops on its own: a batch that stopped only once all had converged gave a body
    # other numbers beside a slower one than alone (results depended on the batch's make-up)
    moving = np.ones(len(X0), bool)
    for _ in range(config.iterations):
        X = X0 + tb[:, None]
        Z = X[..., 2]  # unchanged: the shift is parallel to the image plane
        r = np.stack([fx * X[..., 0] / Z + cx, fy * X[..., 1] / Z + cy], -1) - target
        norm = np.linalg.norm(r, axis=-1)
        ww = w * np.where(norm <= delta, 1.0, delta / np.maximum(norm, 1e-9))  # Huber IRLS
        jx, jy = fx / Z, fy / Z  # d(u)/d(tx), d(v)/d(ty); the two axes decouple
        step_x = -(ww * jx * r[..., 0]).sum(1) / np.maximum((ww * jx * jx).sum(1), 1e-12)
        step_y = -(ww * jy * r[..., 1]).sum(1) / np.maximum((ww * jy * jy).sum(1), 1e-12)
        tb[:, 0] += np.where(moving, step_x, 0.0)
        tb[:, 1] += np.where(moving, step_y, 0.0)
        moving &= np.maximum(np.abs(step_x), np.abs(step_y)) >= 1e-6
        if not moving.any():
            break
    sane = np.isfinite(tb).all(1)
    t[np.flatnonzero(usable)[sane]] = tb[sane]
    return t
