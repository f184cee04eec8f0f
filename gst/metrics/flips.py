"""Whole-body left/right flips of the input landmarks, found against the reference.

BlazePose sometimes labels a person's left side as right and vice versa for the whole body
(mostly in side-on views). A network fed those landmarks turns the body the other way, and such
crops score several times the error of the others (docs/landmark_prior.md, "Gravity": 15 of 144
demo crops at 241 mm; 55-61 of the lab's 800 at 334 mm). The evaluation counts them, so a user
sees how much of the error is the detector's reading rather than the network's.

A crop's landmarks are mirrored when both its hip pair and its shoulder pair lie nearer the
opposite side's reference joints (projected into the crop) than their own.
"""

from __future__ import annotations

import numpy as np
import torch

from calibration.camera import project_points_torch
from gst.body.markers import BLAZEPOSE_MIRROR

# (left, right) BlazePose landmark and body-model joint indices of the pairs that are compared
_LANDMARK_PAIRS = ((23, 24), (11, 12))  # hips, shoulders
_JOINT_PAIRS = ((1, 2), (16, 17))  # SMPL layout: left/right hip, left/right shoulder


def landmark_sides(
    landmarks: np.ndarray, reference2d: np.ndarray, min_confidence: float = 0.5
) -> np.ndarray:
    """(N,) int8: +1 where the (N, 33, 3) landmarks (u, v, confidence) put both the hip pair and
    the shoulder pair on their own sides of the reference joints (N, 24, 2) in the same pixels,
    -1 where both pairs lie nearer the opposite side's joints (mirrored), 0 otherwise (the pairs
    disagree, or a compared landmark is missing or below `min_confidence`)."""
    lm = np.asarray(landmarks, np.float64)
    ref = np.asarray(reference2d, np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (33, 3) or ref.shape != (len(lm), 24, 2):
        raise ValueError(
            f"landmark sides: landmarks (N, 33, 3) and reference (N, 24, 2) expected, got "
            f"{lm.shape} and {ref.shape}"
        )
    crossed_all = np.ones(len(lm), dtype=bool)
    own_all = np.ones(len(lm), dtype=bool)
    for usable, same, crossed in _pair_distances(
        lm, ref, _LANDMARK_PAIRS, _JOINT_PAIRS, min_confidence
    ):
        crossed_all &= usable & (crossed < same)
        own_all &= usable & (same < crossed)
    return own_all.astype(np.int8) - crossed_all.astype(np.int8)


def _pair_distances(lm, ref, landmark_pairs, joint_pairs, min_confidence):
    """Per (left, right) pair: (N,) usable (both landmarks there and confident), the summed
    distance of each landmark to its own side's reference joint, and to the other side's."""
    for (ll, lr), (jl, jr) in zip(landmark_pairs, joint_pairs, strict=True):
        a, b = lm[:, ll], lm[:, lr]
        usable = (
            np.isfinite(a).all(1)
            & np.isfinite(b).all(1)
            & (np.minimum(a[:, 2], b[:, 2]) >= min_confidence)
        )
        d = lambda p, j: np.linalg.norm(p[:, :2] - ref[:, j], axis=1)  # noqa: E731
        yield usable, d(a, jl) + d(b, jr), d(a, jr) + d(b, jl)


# (left, right) landmark and joint pairs of the limbs, for the whole-body check of a swap:
# hips, knees, ankles, shoulders, elbows, wrists
_LIMB_LANDMARK_PAIRS = ((23, 24), (25, 26), (27, 28), (11, 12), (13, 14), (15, 16))
_LIMB_JOINT_PAIRS = ((1, 2), (4, 5), (7, 8), (16, 17), (18, 19), (20, 21))


def surely_mirrored(
    landmarks: np.ndarray,
    reference2d: np.ndarray,
    min_separation: float,
    margin: float = 0.1,
    min_confidence: float = 0.5,
) -> np.ndarray:
    """(N,) bool: mirrored as `mirrored_landmarks` finds it, and sure enough to swap the labels
    for training: the reference's hips and shoulders each stand at least `min_separation` px
    apart (side-on, a few px apart, the test reads noise), and exchanging left and right over
    all the limbs' confident landmarks lowers their total distance to the reference joints by
    more than `margin` (a review found a crop whose correct arms the torso's test swapped, 3-11
    px from the truth before and 78-99 after)."""
    lm = np.asarray(landmarks, np.float64)
    ref = np.asarray(reference2d, np.float64)
    sure = mirrored_landmarks(lm, ref, min_confidence)
    for jl, jr in _JOINT_PAIRS:
        sure &= np.linalg.norm(ref[:, jl] - ref[:, jr], axis=1) >= min_separation
    own = np.zeros(len(lm))
    swapped = np.zeros(len(lm))
    limbs = _pair_distances(lm, ref, _LIMB_LANDMARK_PAIRS, _LIMB_JOINT_PAIRS, min_confidence)
    for usable, same, crossed in limbs:
        own += np.where(usable, same, 0.0)
        swapped += np.where(usable, crossed, 0.0)
    return sure & (swapped < (1.0 - margin) * own)


def mirrored_landmarks(
    landmarks: np.ndarray, reference2d: np.ndarray, min_confidence: float = 0.5
) -> np.ndarray:
    """(N,) bool: the (N, 33, 3) landmarks (u, v, confidence) are left/right mirrored against
    the reference joints (N, 24, 2) in the same pixels (`landmark_sides` -1). False where a
    compared landmark is missing or below `min_confidence`."""
    return landmark_sides(landmarks, reference2d, min_confidence) < 0


def reference_in_crops(
    joints_world: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor
) -> np.ndarray:
    """(N, 24, 2) crop pixels of the reference joints (N, 24, 3) in world coordinates, through
    each crop's camera (R, t world-to-camera; K the crop's intrinsics; crops are undistorted)."""
    d = torch.float64
    return project_points_torch(joints_world.to(d), K.to(d), R.to(d), t.to(d)).numpy()


def unmirror(landmarks, mirrored):
    """A copy of (N, 33, C) landmarks (numpy or torch) with the left/right labels of the rows
    `mirrored` (N,) bool exchanged."""
    out = landmarks.clone() if isinstance(landmarks, torch.Tensor) else np.array(landmarks)
    rows = np.flatnonzero(np.asarray(mirrored, dtype=bool))
    if len(rows):
        out[rows] = landmarks[rows][:, np.array(BLAZEPOSE_MIRROR)]  # a writable copy: torch warns
    return out
