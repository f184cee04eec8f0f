"""Distillation from the rig: the fused bodies (`gst.fuse`) as pseudo-3D targets of GST training.

The fusion triangulates every camera's BlazePose landmarks and fits one body per person over
the clip (docs/formats/fused_bodies.md); its joints, orientation, local rotations and shape
become targets of the single-view prediction from each crop of that person and frame, weighted
by the fit's evidence: a joint seen by >= `full_views` cameras counts fully, fewer views less,
a gap-filled joint (< 2 views) `gap_weight`; joints without a landmark (spine, neck, collars)
take their frame's mean; frames the fit filled alone (`observed` False) and people never seen
by two cameras at once (`single_view`) get no target. No 3D label is used.

Held-out data never reaches a target: the teacher (`Teacher`; the rig's is
`gst.lift.teacher.RigTeacher`) fits the bodies with the fuse stage's own settings on the crops'
landmarks after removing every held-out camera's and every held-out frame's landmarks
(`teacher_landmarks`: confidence 0, position NaN), so the fit sees training cameras in
training frames only; only when nothing is held out does it take the fuse stage's
`fused/bodies.parquet` as it is. Targets are then attached to training crops only
(`distill_targets(..., allowed=...)`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import pyarrow.parquet as pq
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gst.model.assemble import BodyPrediction
from gst.train.distill_targets import DistillTargets
from gst.train.views import CropSet

log = logging.getLogger("gst.train")

__all__ = [
    "FusedBodies",
    "read_fused_bodies",
    "teacher_landmarks",
    "training_rows",
    "Teacher",
    "distill_targets",
    "distill_terms",
]


@dataclass
class FusedBodies:
    """Rows of a fused bodies file (one per person and frame)."""

    person_id: np.ndarray  # (R,)
    frame: np.ndarray  # (R,)
    joints: np.ndarray  # (R, 24, 3) world, metres
    global_orient: np.ndarray  # (R, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (R, 23, 3) axis-angle
    betas: np.ndarray  # (R, nb)
    joint_views: np.ndarray  # (R, 24) cameras whose triangulation used the joint's landmarks
    gap_filled: np.ndarray  # (R, 24) bool
    observed: np.ndarray  # (R,) bool
    single_view: np.ndarray  # (R,) bool
    fps: float
    settings: dict  # the fusion's settings (FuseOptions as JSON)
    cameras: list[str]
    has_landmarks: np.ndarray  # (24,) bool: joints some landmark observes (the file's table)

    def __len__(self) -> int:
        return len(self.frame)


def read_fused_bodies(path: str | Path) -> FusedBodies:
    """Read `fused/bodies.parquet` (docs/formats/fused_bodies.md)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"fused bodies not found: {path} (run `python -m pipeline run fuse`, or train with "
            "distill=false)"
        )
    table = pq.read_table(path)
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    missing = [
        c
        for c in ("frame", "person_id", "joints3d", "global_orient", "body_pose", "betas",
                  "joint_views", "joint_gap_filled", "observed", "single_view")
        if c not in table.column_names
    ]  # fmt: skip
    if missing or "gst.fused" not in meta:
        raise ValueError(
            f"{path}: not a fused bodies file (missing columns {missing} or 'gst.fused' metadata)"
        )

    def arr(name: str, width: int, dtype=np.float64) -> np.ndarray:
        col = table.column(name).combine_chunks()
        flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False), dtype)
        return flat.reshape(len(table), width) if width > 1 else flat

    n = len(table)
    nb = len(table.column("betas")[0]) if n else 10
    fused_meta = json.loads(meta["gst.fused"])
    joint_names = json.loads(meta.get("gst.joint_names", "[]"))
    observed_by = fused_meta.get("joint_landmarks", {})
    if len(joint_names) != 24:
        raise ValueError(f"{path}: 'gst.joint_names' must list 24 joints")
    return FusedBodies(
        person_id=table.column("person_id").to_numpy(),
        frame=table.column("frame").to_numpy(),
        joints=arr("joints3d", 72).reshape(n, 24, 3),
        global_orient=arr("global_orient", 3),
        body_pose=arr("body_pose", 69).reshape(n, 23, 3),
        betas=arr("betas", nb),
        joint_views=arr("joint_views", 24, np.int64),
        gap_filled=arr("joint_gap_filled", 24, bool),
        observed=table.column("observed").to_numpy(zero_copy_only=False).astype(bool),
        single_view=table.column("single_view").to_numpy(zero_copy_only=False).astype(bool),
        fps=float(json.loads(meta.get("gst.fps", "30"))),
        settings=json.loads(meta.get("gst.tracking", "{}")),
        cameras=list(fused_meta.get("cameras", [])),
        has_landmarks=np.array([bool(observed_by.get(j)) for j in joint_names]),
    )


def training_rows(
    crops: CropSet, heldout_cameras: set[int], first_heldout_frame: int | None
) -> torch.Tensor:
    """(N,) bool: crops from a training camera in a training frame."""
    keep = ~torch.isin(crops.camera, torch.tensor(sorted(heldout_cameras), dtype=torch.long))
    if first_heldout_frame is not None:
        keep &= crops.frame < first_heldout_frame
    return keep


def teacher_landmarks(landmarks: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """A copy of the crops' (N, 33, 3) landmarks with every row not `allowed` (held-out camera
    or frame) removed: position NaN, confidence 0; the fusion then has no evidence there."""
    out = np.array(landmarks, dtype=np.float32, copy=True)
    drop = ~np.asarray(allowed, bool)
    out[drop, :, :2] = np.nan
    out[drop, :, 2] = 0.0
    return out


class Teacher(Protocol):
    """Fused bodies from the crops' landmarks (N, 33, 3) of the store rows `allowed` (N,) only;
    `work` is a folder it may write into."""

    def __call__(self, landmarks: np.ndarray, allowed: np.ndarray, work: Path) -> FusedBodies: ...


def distill_targets(
    crops: CropSet,
    bodies: FusedBodies,
    allowed: torch.Tensor,
    full_views: int = 3,
    gap_weight: float = 0.1,
) -> DistillTargets:
    """Per-crop targets (module doc); rows not `allowed` and crops without a fused body of
    their (frame, person) get weight 0."""
    n = len(crops)
    index = {
        (int(f), int(p)): i
        for i, (f, p) in enumerate(zip(bodies.frame, bodies.person_id, strict=True))
    }
    row = np.array(
        [index.get((int(f), int(p)), -1) for f, p in zip(crops.frame, crops.person, strict=True)],
        np.int64,
    )
    nb = bodies.betas.shape[1] if len(bodies) else 10
    out = DistillTargets.empty(n, nb)
    has = (row >= 0) & allowed.numpy().astype(bool)
    if not has.any():
        return out
    r = row[has]
    views = bodies.joint_views[r].astype(np.float64)
    gap = bodies.gap_filled[r]
    has_lm = bodies.has_landmarks
    w = np.where(gap, gap_weight, np.clip(views / full_views, 0, 1))
    lm_mean = w[:, has_lm].mean(1)
    w = np.where(has_lm[None], w, lm_mean[:, None])  # joints no landmark observes
    row_w = (bodies.observed[r] & ~bodies.single_view[r]).astype(np.float64)
    f32 = torch.float32
    idx = torch.from_numpy(np.flatnonzero(has))
    out.joints_world[idx] = torch.as_tensor(bodies.joints[r], dtype=f32)
    out.joint_weight[idx] = torch.as_tensor(w, dtype=f32)
    out.global_orient[idx] = axis_angle_to_rotation_matrix(
        torch.as_tensor(bodies.global_orient[r], dtype=f32)
    )
    out.body_pose[idx] = axis_angle_to_rotation_matrix(
        torch.as_tensor(bodies.body_pose[r].reshape(-1, 3), dtype=f32)
    ).reshape(-1, 23, 3, 3)
    out.betas[idx] = torch.as_tensor(bodies.betas[r], dtype=f32)
    out.weight[idx] = torch.as_tensor(row_w, dtype=f32)
    return out


def distill_terms(
    pred: BodyPrediction, R_in: torch.Tensor, targets: DistillTargets
) -> dict[str, torch.Tensor]:
    """Loss terms of a batch's single-view predictions against its targets:
    `distill_joints` (root-relative joints, metres, weighted per joint), `distill_root` (the
    pelvis in the world, metres) and `distill_params` (rotation matrices, the global one in the
    input camera, plus 0.1 x betas, squared errors)."""
    w = targets.weight.to(pred.joints_world)
    wsum = w.sum().clamp_min(1e-6)
    jw = targets.joint_weight.to(w) * w[:, None]
    pj, tj = pred.joints_world, targets.joints_world.to(w)
    rel = (pj - pj[:, :1]) - (tj - tj[:, :1])
    go_cam = R_in.to(w) @ targets.global_orient.to(w)
    rot = torch.cat([go_cam[:, None], targets.body_pose.to(w)], 1)
    nb = min(pred.betas.shape[1], targets.betas.shape[1])
    params = ((pred.rotmats - rot) ** 2).mean((1, 2, 3)) + 0.1 * (
        (pred.betas[:, :nb] - targets.betas[:, :nb].to(w)) ** 2
    ).mean(1)
    return {
        "distill_joints": (jw * rel.norm(dim=-1)).sum() / jw.sum().clamp_min(1e-6),
        "distill_root": (w * (pj[:, 0] - tj[:, 0]).norm(dim=-1)).sum() / wsum,
        "distill_params": (w * params).sum() / wsum,
    }
