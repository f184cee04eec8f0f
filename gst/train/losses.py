"""GST losses (paper Sec. 3.2) and the supervised terms used for pretraining and baselines.

L = 1/M sum_i ( MSE(I_i, I^_i) + w_lpips LPIPS(I_i, I^_i) + w_alpha MSE(alpha_i, M^_i) )
    + w_tight mean_n |delta_n|  (+ w_betas |beta|^2)
Supervised (data with truth): 3D joints (root-relative, metres), 2D joints (crop pixels / crop
size) and body parameters (rotation matrices and betas).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from pydantic import BaseModel, ConfigDict, Field


class LossWeights(BaseModel):
    """Weights of every term; paper defaults for the multi-view terms."""

    model_config = ConfigDict(extra="forbid")
    mse: float = Field(1.0, ge=0)
    lpips: float = Field(0.01, ge=0)
    alpha: float = Field(0.1, ge=0)
    tightness: float = Field(0.1, ge=0)
    betas: float = Field(0.0, ge=0)
    joints3d: float = Field(1.0, ge=0)
    joints2d: float = Field(1.0, ge=0)
    root: float = Field(0.2, ge=0)  # absolute pelvis position in the camera frame (metres)
    params: float = Field(0.5, ge=0)
    # Ours, not the paper's (0 gives its objective): the body's centre within 0.1 m of the
    # triangulated mask centre of its person (gst.train.anchors); used when anchors are known.
    anchor: float = Field(1.0, ge=0)
    # Ours: predicted joints against 2D joints detected in the target views (gst.train.keypoints);
    # used when the crops carry detections (train.keypoints).
    keypoints: float = Field(10.0, ge=0)
    # Ours: distillation from the rig's fused bodies (gst.train.distill; train.distill): the
    # single-view prediction against the fused body of its person and frame.
    distill_joints: float = Field(2.0, ge=0)  # root-relative joints, metres
    distill_root: float = Field(0.5, ge=0)  # pelvis position in the world, metres
    distill_params: float = Field(0.5, ge=0)  # rotation matrices and 0.1 x betas


@dataclass
class LossTerms:
    total: torch.Tensor
    parts: dict[str, torch.Tensor]


def image_terms(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    offsets: torch.Tensor,
    betas: torch.Tensor,
    w: LossWeights,
    lpips=None,
) -> dict[str, torch.Tensor]:
    """rgb/target (B, M, H, W, 3) in [0, 1]; alpha/mask (B, M, H, W); offsets (B, V, 3)."""
    parts = {
        "mse": ((rgb - target) ** 2).mean(),
        "alpha": ((alpha - mask) ** 2).mean(),
        "tightness": offsets.norm(dim=-1).mean(),
        "betas": (betas**2).mean(),
    }
    if w.lpips > 0:
        if lpips is None:
            raise ValueError(
                "the LPIPS weight is > 0 but no LPIPS module was given (the term is never dropped "
                "silently; set lpips weight 0 explicitly to train without it)"
            )
        h, wd = rgb.shape[-3:-1]
        a = rgb.reshape(-1, h, wd, 3).permute(0, 3, 1, 2)
        b = target.reshape(-1, h, wd, 3).permute(0, 3, 1, 2)
        parts["lpips"] = lpips(a, b).mean()
    return parts


def root_relative(joints: torch.Tensor) -> torch.Tensor:
    return joints - joints[:, :1]


def supervised_terms(
    joints_cam: torch.Tensor,
    joints2d: torch.Tensor,
    rotmats: torch.Tensor,
    betas: torch.Tensor,
    gt_joints_cam: torch.Tensor | None,
    gt_joints2d: torch.Tensor | None,
    gt_rotmats: torch.Tensor | None,
    gt_betas: torch.Tensor | None,
    crop_size: int,
    visible: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Terms for whatever truth is present. joints2d in crop pixels (B, J, 2)."""
    parts: dict[str, torch.Tensor] = {}
    if gt_joints_cam is not None:
        parts["joints3d"] = (
            (root_relative(joints_cam) - root_relative(gt_joints_cam)).norm(dim=-1).mean()
        )
        parts["root"] = (joints_cam[:, 0] - gt_joints_cam[:, 0]).norm(dim=-1).mean()
    if gt_joints2d is not None:
        err = ((joints2d - gt_joints2d) / crop_size).norm(dim=-1)
        if visible is not None:
            err = err * visible
            parts["joints2d"] = err.sum() / visible.sum().clamp_min(1)
        else:
            parts["joints2d"] = err.mean()
    if gt_rotmats is not None:
        parts["params"] = ((rotmats - gt_rotmats) ** 2).mean()
        if gt_betas is not None:
            parts["params"] = parts["params"] + 0.1 * ((betas - gt_betas) ** 2).mean()
    return parts


def combine(parts: dict[str, torch.Tensor], w: LossWeights) -> LossTerms:
    weights = w.model_dump()
    total = sum(weights[k] * v for k, v in parts.items() if weights.get(k, 0) > 0)
    if not isinstance(total, torch.Tensor):
        raise ValueError(f"no loss term has a positive weight among {sorted(parts)}")
    return LossTerms(total, {k: v.detach() for k, v in parts.items()})
