"""Distillation from the rig: the fused bodies (`gst.fuse`) as pseudo-3D targets of GST training.

The fusion triangulates every camera's BlazePose landmarks and fits one body per person over
the clip (docs/formats/fused_bodies.md); its joints, orientation, local rotations and shape
become targets of the single-view prediction from each crop of that person and frame, weighted
by the fit's evidence: a joint seen by >= `full_views` cameras counts fully, fewer views less,
a gap-filled joint (< 2 views) `gap_weight`; joints without a landmark (spine, neck, collars)
take their frame's mean; frames the fit filled alone (`observed` False) and people never seen
by two cameras at once (`single_view`) get no target. No 3D label is used.

Held-out data never reaches a target: the teacher (`Teacher`; the rig's is
`gst.lift.teacher.RigTeacher`) fits the bodies with the fuse stage's own settings on the
training cameras' crops in the training frames only (a copy of the store without the others:
neither their landmarks nor their pixels); only when nothing is held out does it take the fuse
stage's `fused/bodies.parquet` as it is. Targets are then attached to training crops only
(`distill_targets(..., allowed=...)`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gst.fuse.tables import FusedBodies
from gst.model.assemble import BodyPrediction
from gst.train.distill_targets import DistillTargets
from gst.train.views import CropSet

log = logging.getLogger("gst.train")
TORSO_JOINTS = (1, 2, 16, 17)  # hips and shoulders, SMPL layout

__all__ = [
    "training_rows",
    "Teacher",
    "distill_targets",
    "distill_terms",
]


def training_rows(
    crops: CropSet, heldout_cameras: set[int], first_heldout_frame: int | None
) -> torch.Tensor:
    """(N,) bool: crops from a training camera in a training frame."""
    keep = ~torch.isin(crops.camera, torch.tensor(sorted(heldout_cameras), dtype=torch.long))
    if first_heldout_frame is not None:
        keep &= crops.frame < first_heldout_frame
    return keep


class Teacher(Protocol):
    """Fused bodies from the crops' landmarks (N, 33, 3) of the store rows `allowed` (N,) only;
    `work` is a folder it may write into. `refit`: fuse again even where a fusion of every row
    could be reused (the landmarks were corrected; gst.lift.teacher.RigTeacher)."""

    def __call__(
        self, landmarks: np.ndarray, allowed: np.ndarray, work: Path, *, refit: bool = False
    ) -> FusedBodies: ...


# BlazePose's shoulders and hips, and the body's (SMPL layout): their midpoint is the same
# whichever way round left and right are read
_TORSO_LANDMARKS = (11, 12, 23, 24)
_TORSO_JOINTS = (16, 17, 1, 2)
# a crop whose confident torso lies farther than this share of the crop's side from its target
# body's shows someone else (a crop the fusion moved to another person keeps its extraction id).
# Measured on the demo's 328 training crops with a target: median 0.01, 99th percentile 0.05,
# one at 0.19 (its landmarks' torso off its body); 24 crops given the other person's id in one
# camera (a review's id switch): 0.36 to 0.54 and more.
MAX_TORSO_OFFSET = 0.12


def distill_targets(
    crops: CropSet,
    bodies: FusedBodies,
    allowed: torch.Tensor,
    full_views: int = 3,
    gap_weight: float = 0.1,
    body_model: str | None = None,
    landmarks: torch.Tensor | None = None,
) -> DistillTargets:
    """Per-crop targets (module doc); rows not `allowed` and crops without a fused body of
    their (frame, person) get weight 0. `body_model`: the trained network's body; fused bodies
    of another body are refused (their pose and shape parameters mean other things). With the
    crops' `landmarks` (N, 33, 3), a crop whose confident torso lies more than
    `MAX_TORSO_OFFSET` of its side from the target body's projected torso gets weight 0: it
    shows another person than the body of its (frame, person) (the fusion's regrouping moves
    such crops to the person they show; the store keeps the extraction's id)."""
    if body_model is not None and bodies.body_model != body_model:
        raise ValueError(
            f"the fused bodies were fitted with body model '{bodies.body_model}' "
            f"(fuse.body_model) and the network trains '{body_model}' (train.body_model): "
            "their pose and shape are no targets for another body; set fuse.body_model to the "
            "same model, or train.distill=false"
        )
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
    if not has_lm.any():  # the joints without one take the others' mean: of nothing, NaN
        raise ValueError(
            "the fused bodies name no joint that a landmark observes (their 'gst.fused' "
            "metadata has no 'joint_landmarks' for their 'gst.joint_names'), so their joints "
            "have no weights; run the fuse stage again, or train.distill=false"
        )
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
    # the root and the parameters of a frame the fit guessed (the pelvis, or every torso joint,
    # gap-filled) weigh as its guessed joints do: they had full weight, as "observed" means only
    # that some crop exists
    out.root_weight[idx] = torch.as_tensor(np.where(gap[:, 0], gap_weight, 1.0), dtype=f32)
    torso_guessed = gap[:, list(TORSO_JOINTS)].all(1)
    out.params_weight[idx] = torch.as_tensor(np.where(torso_guessed, gap_weight, 1.0), dtype=f32)
    if landmarks is not None:
        other = _shows_someone_else(crops, out.joints_world, landmarks, idx)
        out.weight[idx[other]] = 0.0
        if other.any():
            log.info(
                "distill: %d of %d crops with a target show another person than its body "
                "(torso more than %.2f of the crop away): no target",
                int(other.sum()),
                len(idx),
                MAX_TORSO_OFFSET,
            )
    return out


def _shows_someone_else(
    crops: CropSet, joints_world: torch.Tensor, landmarks: torch.Tensor, idx: torch.Tensor
) -> np.ndarray:
    """(len(idx),) bool: the crop's confident torso midpoint (>= 3 of shoulders and hips with
    confidence >= 0.5) lies farther than MAX_TORSO_OFFSET x its side from the target's."""
    from gst.metrics.flips import reference_in_crops

    lm = torch.as_tensor(landmarks)[idx].numpy().astype(np.float64)[:, list(_TORSO_LANDMARKS)]
    seen = np.isfinite(lm).all(-1) & (lm[..., 2] >= 0.5)
    enough = seen.sum(1) >= 3
    ref = reference_in_crops(joints_world[idx], crops.R[idx], crops.t[idx], crops.K[idx])
    ref = ref[:, list(_TORSO_JOINTS)]
    with np.errstate(invalid="ignore", divide="ignore"):
        mid_lm = np.where(seen[..., None], lm[..., :2], 0.0).sum(1) / seen.sum(1)[:, None]
        mid_ref = np.where(seen[..., None], ref, 0.0).sum(1) / seen.sum(1)[:, None]
    offset = np.linalg.norm(mid_lm - mid_ref, axis=1) / crops.crop_size
    return enough & np.isfinite(offset) & (offset > MAX_TORSO_OFFSET)


def distill_terms(
    pred: BodyPrediction, R_in: torch.Tensor, targets: DistillTargets
) -> dict[str, torch.Tensor]:
    """Loss terms of a batch's single-view predictions against its targets:
    `distill_joints` (root-relative joints, metres, weighted per joint), `distill_root` (the
    pelvis in the world, metres) and `distill_params` (rotation matrices, the global one in the
    input camera, plus 0.1 x betas, squared errors)."""
    w = targets.weight.to(pred.joints_world)
    rw = w * targets.root_weight.to(w)
    pw = w * targets.params_weight.to(w)
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
        "distill_root": (rw * (pj[:, 0] - tj[:, 0]).norm(dim=-1)).sum() / rw.sum().clamp_min(1e-6),
        "distill_params": (pw * params).sum() / pw.sum().clamp_min(1e-6),
    }
