"""Appearance learnt on the rig's body: the network's Gaussians posed on the fused body of their
person and frame (the distillation target, `gst.train.distill`) for the multi-view image terms.

Why: the paper renders the Gaussians on the network's own pose. With that pose some 90 mm off
(the demo's tiny network), every Gaussian that lands beside the person in a target view costs
colour there, and the cheapest answer is to shrink and fade them all: after training the demo's
Gaussians had a median scale of 2 mm (12 mm at the start) and opacity 0.24 (0.9), and its
held-out renders were speckled clouds (silhouette IoU 0.38). Posed on the rig's fused body
(about 28 mm from the truth on the demo), the image terms judge the appearance rather than the
pose error. The pose still learns from the distillation and keypoint terms; crops without a
fused body keep the paper's render on their own predicted pose. No 3D label is used: the fused
bodies come from 2D landmarks and the calibration.
"""

from __future__ import annotations

from dataclasses import fields

import torch

from gst.body import BodyModel
from gst.model.assemble import BodyPrediction, PosedGaussians, pose_gaussians
from gst.model.network import GaussianParams
from gst.train.distill_targets import DistillTargets
from gst.train.views import CropSet

__all__ = ["teacher_posed_gaussians", "truth_targets"]


def teacher_posed_gaussians(
    pred: BodyPrediction, targets: DistillTargets, body: BodyModel, vertex_ids: torch.Tensor
) -> PosedGaussians:
    """World-frame Gaussians of `pred` posed on each row's fused body (its shape, local and
    global rotations, its pelvis where the fused pelvis is); rows without a target (weight 0)
    keep `pred.gaussians_world`."""
    own = pred.gaussians_world
    if own is None or pred.gaussian_params is None:
        raise ValueError("teacher_posed_gaussians: the prediction has no Gaussians")
    has = targets.weight > 0
    if not bool(has.any()):
        return own
    dtype, device = own.means.dtype, own.means.device
    t = targets.take(torch.nonzero(has).flatten().cpu())
    nb = body.num_betas
    betas = torch.zeros(len(t), nb, dtype=dtype, device=device)
    k = min(nb, t.betas.shape[1])
    betas[:, :k] = t.betas[:, :k].to(device, dtype)
    posed = body(
        betas,
        t.body_pose.to(device, dtype),
        t.global_orient.to(device, dtype),
        torch.zeros(len(t), 3, dtype=dtype, device=device),
        vertex_ids=vertex_ids,
        return_transforms=True,
    )
    shift = t.joints_world[:, 0].to(device, dtype) - posed.joints[:, 0]
    g = pred.gaussian_params
    rows = has.to(device)
    mine = pose_gaussians(
        GaussianParams(**{f.name: getattr(g, f.name)[rows] for f in fields(g)}),
        posed.vertices + shift[:, None],
        posed.vertex_transforms,
    )
    if bool(has.all()):  # every row has its body (the pretraining; most scene batches)
        return mine
    out = {}
    for f in fields(own):
        merged = getattr(own, f.name).clone()
        merged[rows] = getattr(mine, f.name).to(merged.dtype)
        out[f.name] = merged
    return PosedGaussians(**out)


def truth_targets(crops: CropSet) -> DistillTargets:
    """Targets from a synthetic crop set's exact truth (`gst.train.synthetic_crops`: rotations
    with the global one in the crop's camera, betas, world joints), every row weight 1: the
    rendered pretraining poses the Gaussians on the true body with them."""
    t = crops.truth
    rot = t["rotmats_cam"].float()
    n = rot.shape[0]
    return DistillTargets(
        joints_world=t["joints_world"].float(),
        joint_weight=torch.ones(n, rot.shape[1]),
        global_orient=crops.R.float().transpose(1, 2) @ rot[:, 0],  # camera -> world
        body_pose=rot[:, 1:],
        betas=t["betas"].float(),
        weight=torch.ones(n),
    )
