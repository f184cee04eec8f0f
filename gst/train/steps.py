"""One training step of GST: predict from the input view, render into the target views (the input
view and others of the same person and frame, `gst.train.views.sample_multiview`), compare.

`multiview_step` is the paper's self-supervised objective (no 3D labels). `supervised_step`
adds 3D joints / 2D joints / parameter terms for pretraining and for the paper's 2D and 3D
fine-tuning baselines. Both return (loss, metrics) for `gst.train.trainer.Trainer`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import torch
from torch import nn

from gst.body import BodyModel
from gst.device import module_on
from gst.model.assemble import BodyPrediction, PosedGaussians
from gst.model.inference import predict_bodies
from gst.model.landmarks import camera_up, hide_up
from gst.render import rasterize
from gst.train.anchors import anchor_term
from gst.train.distill import distill_terms
from gst.train.keypoints import keypoint_term, marker_keypoints
from gst.train.losses import LossWeights, combine, image_terms, supervised_terms
from gst.train.occlusion import ignore_occluded, ignored_share, supervised_psnr
from gst.train.teacher_render import teacher_posed_gaussians
from gst.train.views import MultiViewBatch

Supervision = Literal["multiview", "2d", "3d"]


@dataclass
class GSTTask:
    body: BodyModel
    vertex_ids: torch.Tensor
    crop_size: int
    image_size: tuple[int, int]
    weights: LossWeights
    lpips: nn.Module | None = None
    supervision: Supervision = "multiview"
    # the world's up axis of the crops' cameras (`calibration.Rig.up`): with a camera rotation
    # it gives a gravity-aware network (GSTConfig.landmark_gravity) the up direction in the crop
    world_up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    # multi-view image terms on the network's Gaussians posed on the batch's fused bodies where
    # it has them (gst.train.teacher_render), not on the network's own pose
    appearance_on_teacher: bool = False
    # the keypoint term compares the landmarks with virtual markers on the predicted body
    # (gst.body.markers.MarkerModel; None: with the joints themselves)
    markers: nn.Module | None = None

    def to(self, device: torch.device | str) -> GSTTask:
        """This task on `device` (its body model and LPIPS network copied there when they
        live elsewhere; the caller's stay where they are)."""
        return replace(
            self,
            body=module_on(self.body, device),
            vertex_ids=self.vertex_ids.to(device),
            lpips=None if self.lpips is None else module_on(self.lpips, device),
            markers=None if self.markers is None else module_on(self.markers, device),
        )


def predict(
    model: nn.Module,
    task: GSTTask,
    images: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor | None = None,
    t: torch.Tensor | None = None,
    with_gaussians: bool = True,
    with_vertices: bool = False,
    landmarks: torch.Tensor | None = None,
    up: torch.Tensor | None = None,
) -> BodyPrediction:
    """`gst.model.inference.predict_bodies` with a training task's body and sizes; `landmarks`
    (B, 33, 3) are the crops' (ignored by a network without landmark tokens); the cameras' up
    direction is `up`, or else comes from `R` and the task's world up."""
    if up is None and R is not None:
        up = camera_up(R, task.world_up)
    return predict_bodies(
        model, task.body, task.vertex_ids, images, K, task.image_size, R=R, t=t,
        with_gaussians=with_gaussians, with_vertices=with_vertices, crop_size=task.crop_size,
        landmarks=landmarks, up=up,
    )  # fmt: skip


def project(points_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection (crops are undistorted): (B, N, 3) camera points -> (B, N, 2) px, in
    float32 with autocast off (under bf16 autocast the matmul ran in bf16: about half a pixel
    off at 256 px, the size of the 2D terms' own errors)."""
    with torch.autocast(points_cam.device.type, enabled=False):
        points_cam, K = points_cam.float(), K.float()
        z = points_cam[..., 2:].clamp_min(1e-6)
        uv1 = (points_cam / z) @ K.transpose(-1, -2)
        return uv1[..., :2]


def render_predictions(
    pred: BodyPrediction, batch: MultiViewBatch, size: int, gaussians: PosedGaussians | None = None
):
    """Render the prediction's world Gaussians (or `gaussians`) into the batch's target views."""
    g = pred.gaussians_world if gaussians is None else gaussians
    return rasterize(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.colors,
        batch.viewmats,
        batch.K_target,
        size,
        size,
        backgrounds=batch.backgrounds,
    )


def multiview_image_terms(model: nn.Module, batch: MultiViewBatch, task: GSTTask):
    """Predict from the input view, render into the target views, and compare with the targets
    composited on the batch's random backgrounds; pixels where another person hides this one are
    not supervised when the batch knows them. Returns (prediction, render, target, terms)."""
    # a share of the inputs is seen as from an uncalibrated camera (gst.model.landmarks.hide_up)
    up = hide_up(camera_up(batch.R_in, task.world_up))
    pred = predict(
        model, task, batch.input_images, batch.K_in, batch.R_in, batch.t_in, with_gaussians=True,
        landmarks=batch.input_landmarks, up=up,
    )  # fmt: skip
    gaussians = pred.gaussians_world
    if task.appearance_on_teacher and batch.distill is not None:
        gaussians = teacher_posed_gaussians(pred, batch.distill, task.body, task.vertex_ids)
    out = render_predictions(pred, batch, batch.target_images.shape[-2], gaussians)
    mask = batch.target_masks
    target = batch.target_images * mask[..., None] + batch.backgrounds[:, :, None, None, :] * (
        1 - mask[..., None]
    )
    if batch.target_occluders is not None:
        target, mask = ignore_occluded(out.rgb, out.alpha, target, mask, batch.target_occluders)
    parts = image_terms(
        out.rgb,
        out.alpha,
        target,
        mask,
        gaussians.offsets,
        pred.betas,
        task.weights,
        task.lpips,
    )
    if batch.anchors is not None and task.weights.anchor > 0:
        parts["anchor"] = anchor_term(pred.gaussians_world.means.mean(1), batch.anchors)
    if batch.target_keypoints is not None and task.weights.keypoints > 0:
        points = pred.joints_world
        if task.markers is not None and pred.joint_rotations_cam is not None:
            points = marker_keypoints(points, pred.joint_rotations_cam, batch.R_in, task.markers)
        parts["keypoints"] = keypoint_term(
            points,
            batch.viewmats,
            batch.K_target,
            batch.target_keypoints,
            batch.target_images.shape[-2],
        )
    w = task.weights
    if batch.distill is not None and w.distill_joints + w.distill_root + w.distill_params > 0:
        parts.update(distill_terms(pred, batch.R_in, batch.distill))
    return pred, out, target, parts


def multiview_step(
    model: nn.Module, batch: MultiViewBatch, task: GSTTask
) -> tuple[torch.Tensor, dict]:
    _, out, target, parts = multiview_image_terms(model, batch, task)
    terms = combine(parts, task.weights)
    with torch.no_grad():
        ignored = None
        if batch.target_occluders is not None:  # as ignore_occluded leaves them out
            ignored = ignored_share(batch.target_masks, batch.target_occluders)
        terms.parts["psnr"] = supervised_psnr(out.rgb, target, ignored)
    return terms.total, terms.parts


@dataclass
class SupervisedBatch:
    images: torch.Tensor  # (B, S, S, 3) uint8
    K: torch.Tensor  # (B, 3, 3) crop intrinsics
    joints_cam: torch.Tensor | None = None  # (B, 24, 3) truth in the crop's camera frame
    joints2d: torch.Tensor | None = None  # (B, 24, 2) crop pixels
    visible: torch.Tensor | None = None  # (B, 24)
    rotmats: torch.Tensor | None = None  # (B, 24, 3, 3) truth, global orient in camera frame
    betas: torch.Tensor | None = None
    landmarks: torch.Tensor | None = None  # (B, 33, 3) the crops' detections (landmark tokens)
    up: torch.Tensor | None = None  # (B, 3) the world's up in each crop's camera, where known


def supervised_step(
    model: nn.Module, batch: SupervisedBatch, task: GSTTask
) -> tuple[torch.Tensor, dict]:
    """2D supervision uses only 2D joints; 3D uses 3D joints and parameters as well."""
    pred = predict(
        model,
        task,
        batch.images,
        batch.K,
        with_gaussians=False,
        landmarks=batch.landmarks,
        up=batch.up,
    )
    joints2d = project(pred.joints_cam, batch.K)
    use3d = task.supervision == "3d"
    parts = supervised_terms(
        pred.joints_cam,
        joints2d,
        pred.rotmats,
        pred.betas,
        batch.joints_cam if use3d else None,
        batch.joints2d,
        batch.rotmats if use3d else None,
        batch.betas if use3d else None,
        task.crop_size,
        batch.visible,
    )
    terms = combine(parts, task.weights)
    if batch.joints_cam is not None:
        with torch.no_grad():
            rel = (pred.joints_cam - pred.joints_cam[:, :1]) - (
                batch.joints_cam - batch.joints_cam[:, :1]
            )
            terms.parts["mpjpe_mm"] = 1000 * rel.norm(dim=-1).mean()
    return terms.total, terms.parts
