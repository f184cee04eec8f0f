"""How far the network's projected body joints (`joints2d`) lie from the landmark model's 2D
joints (`landmarks2d`) in the same rows: a check of the 3D body against the 2D evidence of the
frame, available on any video (no truth needed).

Thirteen joints have a landmark counterpart (as in gst.fuse.joint_map and
gst.train.keypoints): pelvis (mid-hips), hips, knees, ankles, shoulders, elbows and wrists.

A BlazePose landmark is not the body model's joint: its "hip" sits a few centimetres from the
hip joint, and the body model's pelvis is above the middle of its hips. So `joints_vs_landmarks`
carries a systematic offset even for a perfect body (on the lab capture at 1088x1920, the
network's joints lie a median 8-13 px from its own BlazePose points). `markers_vs_landmarks`
compares like with like: the body's own BlazePose points (the virtual markers of
gst.body.markers, posed from the row's parameters and projected with the video's camera) against
the landmarks, the pelvis as the middle of the two hip markers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import torch

from gst.body.markers import BLAZEPOSE_NAMES, MarkerModel
from gst.body.model import BodyModel
from gst.track.read import column_array, landmark_array
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
    lm = landmark_array(table)
    if lm is None:
        return LandmarkAgreement(None, None, 0, {})
    return _agreement(column_array(table, "joints2d")[:, COMPARED_INDEX], lm, min_confidence)


@torch.no_grad()
def body_markers_2d(
    table: pa.Table,
    body: BodyModel,
    markers: MarkerModel,
    project: Callable[[np.ndarray], np.ndarray],
    batch: int = 4096,
) -> np.ndarray:
    """(N, 33, 2) the rows' bodies' own BlazePose points (virtual markers), posed from the
    camera-frame parameters and put through `project` ((N, M, 3) camera points -> pixels, the
    projection `joints2d` went through)."""
    cols = ("betas", "body_pose", "global_orient_cam", "transl_cam")
    params = {c: column_array(table, c) for c in cols}
    out = []
    for a in range(0, table.num_rows, batch):
        p = {c: torch.tensor(v[a : a + batch], dtype=body.dtype) for c, v in params.items()}
        posed = body(
            p["betas"][:, : body.num_betas],
            p["body_pose"],
            p["global_orient_cam"],
            p["transl_cam"],
            vertex_ids=markers.vertex_ids,
            return_transforms=True,
        )
        out.append(project(markers.positions(posed).double().numpy()))
    return np.concatenate(out) if out else np.zeros((0, len(BLAZEPOSE_NAMES), 2))


def markers_vs_landmarks(
    table: pa.Table, markers_2d: np.ndarray, min_confidence: float = 0.5
) -> LandmarkAgreement:
    """Like `joints_vs_landmarks`, with the body's own BlazePose points (`markers_2d`, (N, 33, 2)
    from `body_markers_2d`) in place of its joints: no offset between two definitions of a
    joint."""
    lm = landmark_array(table)
    if lm is None:
        return LandmarkAgreement(None, None, 0, {})
    points = np.stack([markers_2d[:, idx].mean(axis=1) for idx in _LANDMARKS], axis=1)
    return _agreement(points, lm, min_confidence)


def _agreement(points: np.ndarray, lm: np.ndarray, min_confidence: float) -> LandmarkAgreement:
    """(N, 13, 2) body points of the COMPARED_JOINTS against (N, 33, 3) landmarks."""
    empty = LandmarkAgreement(None, None, 0, {})
    target, w = landmark_targets(lm, min_confidence)
    d = np.linalg.norm(points - target, axis=-1)  # (N, 13)
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
