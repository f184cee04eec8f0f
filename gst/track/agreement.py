"""How far the network's projected body joints (`joints2d`) lie from the landmark model's 2D
joints (`landmarks2d`) in the same rows: a check of the 3D body against the 2D evidence of the
frame, available on any video (no truth needed).

Thirteen joints have a landmark counterpart (as in gst.fuse.joint_map and
gst.train.keypoints): pelvis (mid-hips), hips, knees, ankles, shoulders, elbows and wrists. A
BlazePose hip is not exactly the body model's hip joint, so a perfect network still shows a few
pixels of systematic offset there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from gst.body.markers import BLAZEPOSE_NAMES
from gst.track.read import column_array
from gst.track.schema import SMPL_JOINT_NAMES

# body-model joint -> the landmarks averaged for it (same names on both sides otherwise)
COMPARED_JOINTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("left_hip", "right_hip"),
    **{
        f"{side}_{part}": (f"{side}_{part}",)
        for part in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist")
        for side in ("left", "right")
    },
}


COMPARED_INDEX = np.array([SMPL_JOINT_NAMES.index(j) for j in COMPARED_JOINTS])
_LANDMARKS = [[BLAZEPOSE_NAMES.index(n) for n in lms] for lms in COMPARED_JOINTS.values()]


@dataclass(frozen=True)
class LandmarkAgreement:
    median_px: float | None  # over every compared (row, joint) pair; None when there is none
    p90_px: float | None
    pairs: int  # (row, joint) pairs compared
    per_joint_median_px: dict[str, float]

    def to_dict(self) -> dict:
        return {
            "median_px": self.median_px,
            "p90_px": self.p90_px,
            "pairs": self.pairs,
            "per_joint_median_px": self.per_joint_median_px,
        }


def landmark_targets(landmarks: np.ndarray, min_confidence: float) -> tuple:
    """(N, 13, 2) landmark positions of the COMPARED_JOINTS (the mean of their landmarks) from
    (N, 33, 3) landmarks, and (N, 13) weights: the least confidence among them, 0 where any is
    below `min_confidence` or not a number."""
    lm = np.asarray(landmarks, np.float64)
    uv = np.stack([lm[:, idx, :2].mean(axis=1) for idx in _LANDMARKS], axis=1)
    conf = np.stack([lm[:, idx, 2].min(axis=1) for idx in _LANDMARKS], axis=1)
    ok = np.isfinite(uv).all(-1) & np.isfinite(conf) & (conf >= min_confidence)
    return np.where(ok[..., None], uv, 0.0), np.where(ok, conf, 0.0)


def joints_vs_landmarks(table: pa.Table, min_confidence: float = 0.5) -> LandmarkAgreement:
    """Distances (px) between `joints2d` and the landmarks of the same joints, over the rows
    that have landmarks, counting landmarks at least `min_confidence` sure."""
    empty = LandmarkAgreement(None, None, 0, {})
    if "landmarks2d" not in table.column_names or table.num_rows == 0:
        return empty
    j2 = column_array(table, "joints2d")
    lm = np.concatenate(
        [column_array(table, "landmarks2d"), column_array(table, "landmarks_conf")[..., None]], -1
    )
    target, w = landmark_targets(lm, min_confidence)
    d = np.linalg.norm(j2[:, COMPARED_INDEX] - target, axis=-1)  # (N, 13)
    usable = (w > 0) & np.isfinite(d)
    all_d, per = [], {}
    for k, name in enumerate(COMPARED_JOINTS):
        if usable[:, k].any():
            per[name] = float(np.median(d[usable[:, k], k]))
            all_d.append(d[usable[:, k], k])
    if not all_d:
        return empty
    d = np.concatenate(all_d)
    return LandmarkAgreement(float(np.median(d)), float(np.percentile(d, 90)), int(len(d)), per)
