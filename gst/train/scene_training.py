"""GST training on a scene's own crops: multi-view with no 3D labels, or the 2D/3D baselines.

Starts from `models/pretrain.pt` (or an HMR2 checkpoint with the `huge` preset), renders each
prediction into the other views of the same person and compares with what those cameras saw.
Held-out cameras are never trained on: they measure novel-view quality. On synthetic scenes the
report also gives MPJPE against the truth before and after training. Writes `models/gst.pt`,
`models/example.ply` (one predicted splat) and `reports/train/`.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import torch
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from gst.atomic import atomic_write_text
from gst.body import load_body_model
from gst.detect.blazepose import import_litert
from gst.detect.weights import model_paths
from gst.device import check_device_name, resolve_device
from gst.fuse.observations import without_projected
from gst.metrics.flips import reference_in_crops, surely_mirrored, unmirror
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import keep_model, load_checkpoint, network_from_checkpoint
from gst.model.hmr2_import import import_hmr2
from gst.model.inference import check_body_fits_network, check_same_body
from gst.model.presets import get_preset
from gst.param_types import NAMES_FILE
from gst.render.ply import write_gaussians_ply
from gst.train.anchors import mask_centre_anchors
from gst.train.distill import Teacher, distill_targets, training_rows
from gst.train.evaluation import (
    PoseMetrics,
    ViewMetrics,
    novel_view_metrics,
    novel_view_pairs,
    pose_metrics,
)
from gst.train.keypoints import keypoints_from_landmarks, projected_rows, store_landmarks
from gst.train.losses import LossWeights
from gst.train.occlusion import occluder_masks
from gst.train.recipe import (
    FitOptions,
    FitSummary,
    Rehearsal,
    build_network,
    fit_gst,
    make_task,
)
from gst.train.scene_truth import attach_scene_truth, select_rows
from gst.train.steps import predict
from gst.train.trainer import TrainConfig
from gst.train.views import CropSet, heldout_frame_start, load_cropset

log = logging.getLogger("gst.train")


class TrainSettings(BaseModel):
    """Settings of GST training on a scene's crops (the `train` stage's parameters)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    # multiview: GST (no labels). 2d / 3d: the paper's Table 1 baselines, fine-tuned on the
    # synthetic truth's 2D joints / 3D joints and parameters (synthetic scenes only).
    supervision: Literal["multiview", "2d", "3d"] = "multiview"
    # which crop store to train on: the extraction's (`crops/crops.h5`) or the crops the fuse
    # stage cut again from the fitted bodies (`bodycrops/crops.h5`; docs/fuse.md: those come
    # from bodies fitted on every camera and frame, held-out ones included)
    crops: Literal["extract", "bodycrops"] = "extract"
    init: Literal["pretrain", "hmr2"] = "pretrain"  # start from models/pretrain.pt or HMR2
    hmr2_checkpoint: Path | None = (
        None  # with init=hmr2 (huge preset); loaded with weights_only=True
    )
    # "anny", or a path to your SMPL file (docs/body_model.md)
    body_model: str = Field("anny", json_schema_extra=NAMES_FILE)
    heldout_cameras: list[str] | None = None  # default: the rig's last camera
    steps: PositiveInt = 1000  # optimiser steps
    batch_size: PositiveInt = 8  # input crops per step (their groups' other views: targets)
    lr: PositiveFloat = 1e-3  # Gaussian head (tokens, attribute heads)
    # backbone + SMPL head (None: `lr` for everything). With the keypoint term the body can
    # learn (demo: -27% MPJPE at 3e-4); without it, keep it low: from a poor start the
    # photometric gradient alone drags the pose away (+11% at 1e-4, -2% at 1e-5; docs/training.md).
    body_lr: PositiveFloat | None = 3e-4
    # supervision 2d/3d (the Table 1 baselines): the whole network
    supervised_lr: PositiveFloat = 1e-4
    freeze_backbone: bool = (
        False  # the paper freezes HMR2's ViT; our small pretrained ViT is tuned too
    )
    num_targets: PositiveInt = 4  # cameras each crop's Gaussians are rendered into per step
    render_size: PositiveInt = 64  # side (px) of those renders
    ignore_occluders: bool = True  # other people's pixels in a target crop are not supervised
    anchor: bool = True  # pull the body towards its triangulated mask centre (losses.anchor weight)
    # Reproject the joints into the target views against 2D joints the BlazePose landmark model
    # detects in their crops (losses.keypoints; gst.train.keypoints). Needs the `detect` extra and
    # `python -m gst.detect fetch`. Ours, not the paper's; false gives its objective.
    keypoints: bool = True
    # Frames held out in time: the last share of the clip's frames never enters any training
    # term (distillation included) or the checkpoint choice; `evaluate` scores them (0: none).
    heldout_frames: float = Field(0.25, ge=0, lt=1)
    # Distillation from the rig (gst.train.distill): the fused bodies of the `fuse` stage, refitted
    # without held-out cameras and frames, as pseudo-3D targets (losses.distill_*). Ours.
    distill: bool = True
    # Feed each input crop's BlazePose landmarks to a network with landmark tokens (the store's
    # `landmarks`, else detected); false gives such a network the image-only path.
    landmarks: bool = True
    landmark_dropout: float = Field(0.1, ge=0, le=1)  # share of inputs trained without them
    # With distillation: a training crop whose landmarks the rig's fused body shows left/right
    # mirrored (BlazePose's whole-body flips, gst.metrics.flips) is trained on them un-mirrored,
    # so the network learns the body its landmarks describe (docs/training.md, "Mirrored
    # landmarks"); held-out crops are never touched.
    unmirror_landmarks: bool = True
    # Rehearse the render-free landmark prior beside every multi-view step (gst.lift.rehearsal):
    # the pretraining's supervised terms on `rehearsal_batch` simulated detections, weighted by
    # `rehearsal`, so that the scene's few people do not overwrite what it learnt of everyone
    # else (0: off; networks without landmark tokens have nothing to rehearse; docs/training.md
    # "Prior rehearsal": on unseen people the trained demo model stays at the pretrained one's
    # error instead of losing 5-15 mm, on the demo's own held-out frames within noise).
    rehearsal: float = Field(10.0, ge=0)
    rehearsal_batch: int = Field(32, ge=1)  # simulated detections per rehearsal step
    # With distillation: the multi-view image terms render the network's Gaussians posed on the
    # rig's fused body of each crop's person and frame instead of on the network's own pose, so
    # that its pose error does not teach the Gaussians to shrink and fade
    # (gst.train.teacher_render; docs/training.md "Appearance on the rig's body").
    appearance_on_teacher: bool = True
    losses: LossWeights = LossWeights()  # loss weights (docs/training.md)
    threads: PositiveInt | None = None  # torch CPU threads (default: torch's choice)
    # where the network trains (gst.device): auto is the GPU when PyTorch sees one, else the CPU
    device: Annotated[str, AfterValidator(check_device_name)] = "auto"
    amp: bool = False  # bf16 autocast (GPUs; huge preset with gsplat: 1.9x a step, docs/gpu.md)


def _initial_network(p: TrainSettings, pretrained: Path, body):
    if p.init == "hmr2":
        if p.hmr2_checkpoint is None:
            raise ValueError(
                "train.init=hmr2 needs train.hmr2_checkpoint=PATH (an HMR2 .ckpt or state dict)"
            )
        cfg = get_preset("huge")
        net, ids, groups = build_network(cfg, body)
        report = import_hmr2(net, p.hmr2_checkpoint)
        log.info("HMR2 import: %s", report.summary())
        return net, ids, groups
    ckpt = load_checkpoint(pretrained)
    # compared by content where the specs differ: the same file at another path is that body
    check_same_body(ckpt, p.body_model, lambda: body, "models/pretrain.pt", "train.body_model")
    net = network_from_checkpoint(ckpt, pretrained)
    check_body_fits_network(net, body, pretrained)  # the spec may resolve to another body here
    return net, ckpt.vertex_ids.numpy(), ckpt.group_index.numpy()


def _contact_sheet(images, path: Path, max_rows: int = 8) -> None:
    rows = []
    for inputs, renders, targets in images:
        for i in range(len(renders)):
            size = renders.shape[-1]
            inp = cv2.resize(inputs[i].numpy(), (size, size), interpolation=cv2.INTER_AREA)
            rnd = (renders[i].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
            tgt = (targets[i].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
            rows.append(np.concatenate([inp, rnd, tgt], axis=1))
            if len(rows) >= max_rows:
                break
    if rows:
        sheet = np.concatenate(rows, axis=0)
        sheet = cv2.resize(
            sheet, (sheet.shape[1] * 2, sheet.shape[0] * 2), interpolation=cv2.INTER_NEAREST
        )
        cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


@dataclass(frozen=True)
class PreparedCrops:
    """The crops training sees, the held-out cameras and the first held-out frame (None: none)."""

    crops: CropSet
    heldout_cameras: list[str]
    first_heldout_frame: int | None


def _unmirrored(crops: CropSet, landmarks: torch.Tensor, targets) -> torch.Tensor:
    """`landmarks` with the left/right labels exchanged on the crops that have a fused-body
    target (`targets`, gst.train.distill.DistillTargets) and whose hips and shoulders that body
    shows mirrored."""
    rows = torch.nonzero(targets.weight > 0)[:, 0]
    if len(rows) == 0:
        return landmarks
    reference = reference_in_crops(
        targets.joints_world[rows], crops.R[rows], crops.t[rows], crops.K[rows]
    )
    flags = np.zeros(len(landmarks), dtype=bool)
    # only where sure: side-on, with hips and shoulders a few px apart, the test read noise
    flags[rows.numpy()] = surely_mirrored(
        landmarks[rows].numpy(), reference, min_separation=0.05 * crops.crop_size
    )
    log.info(
        "distill: %d of %d training crops have left/right mirrored landmarks; trained un-mirrored",
        int(flags.sum()),
        len(rows),
    )
    return unmirror(landmarks, flags)


def prepare_crops(
    p: TrainSettings,
    crops_h5: Path,
    synth_dir: Path | None,
    scene: str = "scene",
    progress=None,
    *,
    feed_landmarks: bool = False,
    teacher: Teacher | None = None,
    work: Path | None = None,
) -> PreparedCrops:
    """The scene's crops with what training needs: truth on synthetic scenes (only rows with
    truth for the 2d/3d baselines), occluder masks, label-free anchors, the crops' landmarks
    (fed to landmark tokens when `feed_landmarks`) and the 2D joints they give, distillation
    targets from the `teacher` (the rig: `gst.lift.teacher.RigTeacher`; `work`: a folder it may
    write into), the held-out cameras and frames."""
    crops, boxes = load_cropset(crops_h5)
    multiview = p.supervision == "multiview"
    heldout = p.heldout_cameras if p.heldout_cameras is not None else crops.camera_names[-1:]
    unknown = [c for c in heldout if c not in crops.camera_names]
    if unknown:
        raise ValueError(
            f"train.heldout_cameras {unknown} are not cameras of {crops_h5} ({crops.camera_names})"
        )
    training_cameras = [c for c in crops.camera_names if c not in heldout]
    if multiview and len(training_cameras) < 2:
        # said before the landmarks are read and the teacher fuses (minutes): the trainer's
        # "no training samples" came only after both
        raise ValueError(
            f"train.heldout_cameras {list(heldout)} leave {training_cameras} of {crops_h5}'s "
            f"cameras {crops.camera_names} to train on: multi-view training needs >= 2"
        )
    cut = heldout_frame_start(crops.frame, p.heldout_frames)
    held_idx = {crops.camera_names.index(c) for c in heldout}
    landmarks = None
    projected = None
    if feed_landmarks or (multiview and (p.keypoints or p.distill)):
        # Landmarks the extraction projected from the rig's skeleton hold every camera's
        # evidence, the held-out ones included: every such row is read again by the landmark
        # model (training rows too: their keypoint targets and tokens would carry it), and the
        # teacher gets them with no confidence, as the fuse stage's fusion does.
        projected = projected_rows(crops_h5, len(crops))
        landmarks, source = store_landmarks(
            crops_h5, crops.images, progress=progress, reread=np.ones(len(crops), bool)
        )
        log.info(
            "landmarks (%s): %d of %d crops have one with confidence >= 0.5",
            source,
            int((torch.nan_to_num(landmarks[..., 2]).amax(1) >= 0.5).sum()),
            len(crops),
        )
    if multiview and p.distill:
        if teacher is None:
            raise ValueError(
                "train.distill needs a teacher: the fuse stage's bodies (pipeline.yaml: train "
                "needs fuse), or distill=false"
            )
        if work is None:  # the teacher fuses a subset store there (it failed on Path(None))
            raise ValueError(
                "prepare_crops: train.distill needs `work`, a folder the teacher writes"
            )
        allowed = training_rows(crops, held_idx, cut)
        corrected = False  # whether the rig un-mirrored any landmark (the teacher refits)
        if p.unmirror_landmarks:
            # a first fit of the training crops alone says which of them are mirrored (the fuse
            # stage's own bodies saw the held-out crops); the teacher is then refitted on the
            # corrected landmarks
            first = teacher(
                without_projected(landmarks.numpy(), projected), allowed.numpy(),
                work / "mirrors",
            )  # fmt: skip
            first_targets = distill_targets(
                crops, first, allowed, body_model=p.body_model, landmarks=landmarks
            )
            read = landmarks
            landmarks = _unmirrored(crops, landmarks, first_targets)
            # NaN (a crop where the landmark model found nobody) equals nothing in torch.equal:
            # every such scene counted as corrected and refitted the teacher for nothing
            corrected = not torch.allclose(read, landmarks, rtol=0, atol=0, equal_nan=True)
        # the teacher fuses as the fuse stage does: projected rows carry no confidence
        bodies = teacher(
            without_projected(landmarks.numpy(), projected),
            allowed.numpy(),
            work,
            refit=corrected,
        )
        crops.distill = distill_targets(
            crops, bodies, allowed, body_model=p.body_model, landmarks=landmarks
        )
        log.info(
            "distill: %d of %d crops have a fused-body target (training cameras and frames)",
            int((crops.distill.weight > 0).sum()),
            len(crops),
        )
    if landmarks is not None:  # as read, or un-mirrored by the rig above
        if multiview and p.keypoints:
            crops.keypoints = keypoints_from_landmarks(landmarks)
        if feed_landmarks:
            crops.landmarks = landmarks
    if synth_dir is not None:
        attach_scene_truth(crops, boxes, synth_dir)
        has = crops.truth["has_truth"]
        log.info("truth matched for %d of %d crops", int(has.sum()), len(crops))
        if not multiview:
            crops = select_rows(crops, torch.nonzero(has)[:, 0])  # supervised rows need their truth
    elif not multiview:
        raise ValueError(
            f"train.supervision={p.supervision} needs truth joints, which only synthetic scenes "
            f"have; scene '{scene}' is real: use supervision=multiview"
        )
    if p.ignore_occluders and multiview:
        crops.occluders = occluder_masks(crops)
        log.info(
            "occluders: %.1f%% of crop pixels belong to another person",
            100 * float(crops.occluders.mean()),
        )
    if p.anchor and multiview:
        train_cams = {i for i, c in enumerate(crops.camera_names) if c not in heldout}
        crops.anchors = mask_centre_anchors(crops, cameras=train_cams)  # held-out masks never used
        log.info(
            "anchors: %d of %d crops have a triangulated mask centre",
            int(torch.isfinite(crops.anchors).all(1).sum()),
            len(crops),
        )
    return PreparedCrops(crops, list(heldout), cut)


@dataclass(frozen=True)
class TrainOutputs:
    """Where `train_scene` writes: the kept model, an example splat, the reports, and the run
    folder (checkpoints to resume from; removed when training is done)."""

    model: Path
    example_ply: Path
    reports: Path
    run_dir: Path


@dataclass(frozen=True)
class SceneTrainingSummary:
    """What `train_scene` returns (and writes as reports/train/summary.json): the fit, the
    kept model's pose on the held-out frames (synthetic scenes with held-out frames only:
    `heldout_first_frame` is then set; the pose is None without a crop to score) and its novel
    views at 128 px on the held-out cameras (None without a pair)."""

    fit: FitSummary
    novel_view_128px: ViewMetrics | None
    heldout_first_frame: int | None = None
    heldout_pose: PoseMetrics | None = None

    def to_dict(self) -> dict:
        """summary.json: the fit's fields, then `heldout_frames` (when scored) and
        `best_checkpoint_novel_view_128px`."""
        out = self.fit.to_dict()
        if self.heldout_first_frame is not None:
            pose = {} if self.heldout_pose is None else self.heldout_pose.to_dict()
            out["heldout_frames"] = {"first_frame": self.heldout_first_frame, **pose}
        nv = self.novel_view_128px
        out["best_checkpoint_novel_view_128px"] = {} if nv is None else nv.to_dict()
        return out


def train_scene(
    p: TrainSettings,
    crops_h5: Path,
    pretrained: Path,
    out: TrainOutputs,
    *,
    synth_dir: Path | None = None,
    teacher: Teacher | None = None,
    scene: str = "scene",
    progress=None,
    rehearse: Callable[..., Rehearsal] | None = None,
    world_up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> SceneTrainingSummary | None:
    """Train GST on a scene's crops from the pretrained model (or HMR2); returns the summary
    (None on torchrun ranks other than 0, which only contribute gradients). `teacher`: fused
    bodies for distillation (`gst.lift.teacher.RigTeacher`; needed when `p.distill`).
    `rehearse(body=, net=, weight=, batch_size=, crop_size=)` builds what is rehearsed beside
    each multi-view step when `p.rehearsal > 0` (`gst.lift.rehearsal.PriorRehearsal`).
    `world_up`: the rig's up axis (a gravity-aware network reads it in each crop's camera)."""
    if p.threads:
        torch.set_num_threads(p.threads)
    resolve_device(p.device)  # `device: cuda` without CUDA fails now, not after the crops load
    multiview = p.supervision == "multiview"
    if multiview and (p.keypoints or p.distill) or p.landmarks:
        model_paths()  # missing person models or LiteRT fail now, with the fix, not after loading
        import_litert()
    body = load_body_model(p.body_model)
    net, ids, groups = _initial_network(p, pretrained, body)
    net.freeze_backbone(p.freeze_backbone)
    out.run_dir.mkdir(parents=True, exist_ok=True)
    prepared = prepare_crops(
        p, crops_h5, synth_dir, scene, progress,
        feed_landmarks=p.landmarks and net.landmark_encoder is not None,
        teacher=teacher, work=out.run_dir / "teacher",
    )  # fmt: skip
    crops, heldout, cut = prepared.crops, prepared.heldout_cameras, prepared.first_heldout_frame
    lpips = load_lpips() if p.losses.lpips > 0 else None
    task = make_task(
        body, ids, net.cfg, crops.crop_size, p.losses, lpips, world_up=world_up,
        appearance_on_teacher=p.distill and p.appearance_on_teacher,
    )  # fmt: skip
    lr = p.lr if multiview else p.supervised_lr
    cfg = TrainConfig.for_stage(p.steps, p.batch_size, lr, p.device, p.amp, validations=5)
    run_dir = out.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    # the 2d/3d baselines train everything at supervised_lr
    body_lr = p.body_lr if multiview else None
    rehearsal = None
    if multiview and p.rehearsal > 0 and net.landmark_encoder is None:
        log.info("train: the network has no landmark tokens: no landmark prior to rehearse")
    elif multiview and p.rehearsal > 0:
        if rehearse is None:
            raise ValueError("train.rehearsal > 0 needs a rehearsal (gst.lift.rehearsal)")
        rehearsal = rehearse(
            body=body, net=net, weight=p.rehearsal, batch_size=p.rehearsal_batch,
            crop_size=crops.crop_size,
        )  # fmt: skip
        log.info(
            "train: rehearsing the landmark prior (weight %g, %d simulated crops a step)",
            p.rehearsal,
            p.rehearsal_batch,
        )
    fit = fit_gst(
        net,
        task,
        crops,
        cfg,
        run_dir,
        FitOptions(
            mode=p.supervision,
            num_targets=p.num_targets,
            render_size=p.render_size,
            heldout_cameras=tuple(heldout),
            body_lr=body_lr,
            first_heldout_frame=cut,
            scene=scene,
            crop_store=p.crops,
            landmark_dropout=p.landmark_dropout if crops.landmarks is not None else 0.0,
        ),
        body_spec=p.body_model,
        vertex_ids=ids,
        group_index=groups,
        progress=progress,
        rehearsal=rehearsal,
    )
    if torch.distributed.is_initialized() and torch.distributed.get_rank() != 0:
        return None  # under torchrun the other ranks only contribute gradients
    best = run_dir / "best.pt"
    out.model.parent.mkdir(parents=True, exist_ok=True)
    keep_model(best, out.model)
    net = network_from_checkpoint(load_checkpoint(best), best).eval()
    summary = _write_reports(net, task, crops, heldout, cut, fit, out)
    shutil.rmtree(run_dir)
    b, a = fit.before, fit.after
    log.info(
        "train: MPJPE on training frames %s -> %s mm; held-out PSNR %s -> %s dB",
        _f(b.get("mpjpe_mm"), "mpjpe_mm"),
        _f(a.get("mpjpe_mm"), "mpjpe_mm"),
        _f(b.get("psnr"), "psnr"),
        _f(a.get("psnr"), "psnr"),
    )
    return summary


def _write_reports(
    net, task, crops: CropSet, heldout, cut: int | None, fit: FitSummary, out: TrainOutputs
) -> SceneTrainingSummary:
    """Novel views of the kept model (held-out frames when there are any), an example splat,
    the log and the summary (on synthetic scenes, MPJPE on the held-out frames: reported only,
    never used to choose anything)."""
    reports = out.reports
    reports.mkdir(parents=True, exist_ok=True)
    heldout_idx = {crops.camera_names.index(c) for c in heldout}
    frames = None if cut is None else (cut, int(crops.frame.max()) + 1)
    pairs = novel_view_pairs(crops, heldout_idx, max_pairs=8, frames=frames)
    nv = novel_view_metrics(net, task, crops, pairs, 128, return_images=True)
    _contact_sheet([] if nv is None else nv.images or [], reports / "novel_views.png")
    first_frame = heldout_pose = None
    if cut is not None and "has_truth" in crops.truth:
        rows = torch.nonzero(crops.truth["has_truth"].bool() & (crops.frame >= cut))[:, 0]
        first_frame, heldout_pose = cut, pose_metrics(net, task, crops, rows)
    with torch.no_grad():
        i = torch.tensor([0])
        g = predict(
            net, task, crops.images[i], crops.K[i], crops.R[i], crops.t[i],
            landmarks=None if crops.landmarks is None else crops.landmarks[i],
        ).gaussians_world  # fmt: skip
    write_gaussians_ply(
        out.example_ply, g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.colors[0]
    )
    shutil.copyfile(out.run_dir / "log.csv", reports / "log.csv")
    summary = SceneTrainingSummary(fit, nv, first_frame, heldout_pose)
    atomic_write_text(
        reports / "summary.json", json.dumps(summary.to_dict(), indent=2, default=float)
    )
    _write_markdown(reports / "summary.md", fit, first_frame, heldout_pose)
    return summary


def _f(v, key: str = "") -> str:
    """mm with 1 decimal, dB with 2, fractions (IoU, SSIM, LPIPS, ...) with 3."""
    if v is None:
        return "n/a"
    digits = 1 if key.endswith("_mm") else 2 if "psnr" in key else 3
    return f"{v:.{digits}f}"


def _write_markdown(path: Path, s: FitSummary, first_heldout: int | None, heldout_pose) -> None:
    keys = sorted(set(s.before) | set(s.after))
    lines = [
        "# GST training",
        "",
        f"{s.steps} steps, {s.bad_steps} skipped, {s.seconds:.0f} s; "
        f"{s.train_groups} multi-view training samples; "
        f"held-out cameras: {', '.join(s.heldout)}.",
        "",
        "| metric | before (pretrained) | after (GST) |",
        "|---|---|---|",
    ]
    lines += [f"| {k} | {_f(s.before.get(k), k)} | {_f(s.after.get(k), k)} |" for k in keys]
    if heldout_pose is not None:
        lines.append(
            f"| mpjpe_mm, held-out frames ({first_heldout}-) | | "
            f"{_f(heldout_pose.mpjpe_mm, 'mpjpe_mm')} |"
        )
    lines += [
        "",
        "MPJPE (pelvis-aligned) and PA-MPJPE in mm against the synthetic truth, on training "
        "frames (the held-out frames' row, where there is one, on frames training never saw); "
        "PSNR (dB), SSIM and silhouette IoU on held-out cameras, person composited on black, "
        "rendered at the training size.",
        "",
        "![novel views](novel_views.png)",
        "",
        "Each row: the input crop (a training camera), the prediction rendered into a held-out "
        "camera, what that camera saw.",
    ]
    path.write_text("\n".join(lines) + "\n")
