"""Build a GST network for a body model, and train it on a CropSet.

`fit_gst` is the one entry point used by supervised pretraining, multi-view (GST) training and
the 2D / 3D fine-tuning baselines; `mode` picks the loss:
- "multiview": render into the other views of the same person (the paper's objective);
- "3d" / "2d": supervised on truth joints/parameters (3D) or 2D joints only (baselines);
- "pretrain": supervised 3D plus the multi-view image terms, so the Gaussian head starts sane.
"""

from __future__ import annotations

import logging
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel

from gst.body import BodyModel
from gst.body.subsets import partition_vertices, vertex_subset
from gst.device import move_to, resolve_device
from gst.model.checkpoint import config_to_dict, load_checkpoint
from gst.model.landmarks import camera_up
from gst.model.network import GSTNetwork
from gst.model.presets import GSTConfig
from gst.train.augment import CropJitter, jitter_batch
from gst.train.evaluation import novel_view_metrics, novel_view_pairs, pose_metrics
from gst.train.losses import LossWeights, combine, supervised_terms
from gst.train.steps import (
    GSTTask,
    SupervisedBatch,
    multiview_image_terms,
    multiview_step,
    project,
    supervised_step,
)
from gst.train.trainer import TrainConfig, Trainer
from gst.train.views import CropSet, sample_multiview

log = logging.getLogger("gst.train")


def build_network(
    cfg: GSTConfig, body: BodyModel, seed: int = 0
) -> tuple[GSTNetwork, np.ndarray, np.ndarray]:
    """A fresh network with Gaussians on the preset's vertex subset, grouped into K tokens."""
    torch.manual_seed(seed)
    ids = vertex_subset(body, cfg.vertex_preset)
    rest = (
        body.rest_vertices(torch.zeros(1, body.num_betas), torch.as_tensor(ids))[0]
        .detach()
        .cpu()
        .numpy()
    )
    groups = partition_vertices(rest, K=cfg.num_groups, seed=seed)
    net = GSTNetwork(cfg, groups)
    if net.refiner is not None:
        net.refiner.set_body(body)
    return net, ids, groups


def gaussian_parameter_groups(model: GSTNetwork, lr: float, body_lr: float) -> list[dict]:
    """Optimizer groups: the Gaussian head (tokens and attribute heads) at `lr`, everything else
    (backbone, SMPL head) at `body_lr`. Adam moves every parameter by about its learning rate
    whatever the gradient's size, so one shared rate either leaves the Gaussians frozen or lets
    the weak, noisy photometric gradient on pose and shape drag a pretrained body off the image."""
    gaussian = {id(p) for p in model.gaussian_head.parameters()}
    gate = model.smpl_head.transformer.smpl_image_gate
    # the landmark network's image gate: a few scalars that Adam moves by about the rate per
    # step; at the body's rate they could not open within a scene training's few hundred steps
    fast = gaussian | ({id(gate)} if gate is not None else set())
    trainable = [p for p in model.parameters() if p.requires_grad]
    groups = [
        {"params": [p for p in trainable if id(p) in fast], "lr": lr, "name": "gaussians"},
        {"params": [p for p in trainable if id(p) not in fast], "lr": body_lr, "name": "body"},
    ]
    return [g for g in groups if g["params"]]


@dataclass
class FitOptions:
    mode: str = "multiview"  # multiview | pretrain | 2d | 3d
    num_targets: int = 4  # views rendered per sample (the input view included)
    render_size: int = 64  # target views are rendered at this resolution
    heldout_cameras: tuple[str, ...] = ()  # never used for training; novel-view validation
    val_pairs: int = 48
    val_pose_crops: int = 96
    body_lr: float | None = (
        None  # backbone + SMPL head learning rate (None: the config's lr for all)
    )
    augment: CropJitter | None = None  # re-crop + colour jitter of supervised (2d/3d) batches
    # Frames held out in time: no training term and no checkpoint choice sees frames >= this
    # (None: every frame trains). Recorded in the checkpoint (extra.heldout_frames).
    first_heldout_frame: int | None = None
    # share of multi-view samples whose input landmarks are hidden (a landmark network keeps an
    # image-only path for crops where the detector finds nobody)
    landmark_dropout: float = 0.0
    scene: str | None = None  # recorded in the checkpoint (extra.trained_on.scene)
    # which crop store trained it (extra.trained_on.crop_store): "bodycrops" are cut from
    # bodies fitted on every camera and frame, held-out ones included (evaluate says so)
    crop_store: str = "extract"


class Rehearsal(Protocol):
    """Something rehearsed beside every multi-view step (gst.lift.rehearsal.PriorRehearsal):
    `draw(generator)` its batch, from the trainer's generator (so a resumed run draws the same);
    `terms(model, drawn)` -> (weighted loss, metrics)."""

    def draw(self, generator: torch.Generator) -> object: ...

    def terms(self, model, drawn) -> tuple[torch.Tensor, dict]: ...


@dataclass
class RehearsedBatch:
    """A training batch with the rehearsal's batch beside it."""

    batch: object
    drawn: object


def _rehearsing(step, rehearsal: Rehearsal):
    """`step` on the scene's batch plus the rehearsed prior on its simulated batch."""

    def rehearsed(model, b: RehearsedBatch):
        extra, more = rehearsal.terms(model, b.drawn)
        # its own backward first, outside DDP's gradient sync: DDP refuses two forward passes
        # before one backward; the scene's backward (by the trainer) then reduces the sum
        with model.no_sync() if isinstance(model, DistributedDataParallel) else nullcontext():
            extra.backward()
        loss, parts = step(model, b.batch)
        return loss + extra.detach(), {**parts, **more}

    return rehearsed


def supervised_batch(
    crops: CropSet, idx: torch.Tensor, world_up: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> SupervisedBatch:
    """A supervised batch of crop rows `idx` from their truth (joints, 2D joints, parameters);
    `world_up`: the crops' world's up axis (pretraining worlds are z-up; a scene's is its rig's,
    `GSTTask.world_up`, as validation and tracking read it)."""
    t = crops.truth
    return SupervisedBatch(
        images=crops.images[idx],
        K=crops.K[idx],
        joints_cam=t["joints_cam"][idx],
        joints2d=t["joints2d"][idx],
        visible=t["visible"][idx],
        rotmats=t["rotmats_cam"][idx],
        betas=t["betas"][idx][:, :10],
        landmarks=None if crops.landmarks is None else crops.landmarks[idx],
        up=camera_up(crops.R[idx], world_up),
    )


def _pretrain_step(model, batch, task: GSTTask, crops: CropSet):
    """Supervised 3D terms on the input view plus image terms on the rendered views."""
    pred, _, _, parts = multiview_image_terms(model, batch, task)
    sup = move_to(supervised_batch(crops, batch.input_index.cpu()), pred.joints_cam.device)
    parts.update(
        supervised_terms(
            pred.joints_cam,
            project(pred.joints_cam, sup.K),
            pred.rotmats,
            pred.betas,
            sup.joints_cam,
            sup.joints2d,
            sup.rotmats,
            sup.betas,
            task.crop_size,
            sup.visible,
        )
    )
    terms = combine(parts, task.weights)
    with torch.no_grad():
        rel = (pred.joints_cam - pred.joints_cam[:, :1]) - (sup.joints_cam - sup.joints_cam[:, :1])
        terms.parts["mpjpe_mm"] = 1000 * rel.norm(dim=-1).mean()
    return terms.total, terms.parts


@dataclass(frozen=True)
class FitSummary:
    """What `fit_gst` returns: the training run (`TrainRunSummary`'s fields), the validation
    metrics before and after training (metric name -> value: pose on the validation crops,
    novel views on the held-out cameras, whichever apply), the number of training groups and
    the held-out cameras."""

    steps: int
    bad_steps: int
    best: float | None
    seconds: float
    before: dict[str, float]
    after: dict[str, float]
    train_groups: int
    heldout: list[str]

    def to_dict(self) -> dict:
        """The summary.json layout (the fields in order)."""
        return asdict(self)


def fit_gst(
    model: GSTNetwork,
    task: GSTTask,
    crops: CropSet,
    cfg: TrainConfig,
    out_dir: Path,
    opts: FitOptions,
    *,
    body_spec: str,
    vertex_ids: np.ndarray,
    group_index: np.ndarray,
    progress=None,
    resume: bool = True,
    val_crops: CropSet | None = None,
    rehearsal: Rehearsal | None = None,
    after_from: str = "last",
) -> FitSummary:
    """Train in place; writes last.pt/best.pt (GST checkpoints) and log.csv into `out_dir`.

    `after_from`: the model that the summary's `after` scores and `model` holds on return,
    "last" (the last step's) or "best" (best.pt: the caller keeps that one; the summary scored
    the last step's model while the pretraining kept the best).

    `val_crops`: crops with truth that training never sees (e.g. another world); pose validation
    (and so the best checkpoint) uses them instead of the training crops. `rehearsal`: the
    landmark prior rehearsed beside every multi-view step (gst.lift.rehearsal)."""
    if after_from not in ("last", "best"):
        raise ValueError(f"after_from must be 'last' or 'best', got {after_from!r}")
    device = resolve_device(cfg.device)  # the Trainer keeps the model there
    model.to(device)
    task = task.to(device)
    names = crops.camera_names
    unknown = [c for c in opts.heldout_cameras if c not in names]
    if unknown:
        raise ValueError(f"held-out cameras {unknown} are not in the crop set (cameras: {names})")
    heldout = {names.index(c) for c in opts.heldout_cameras}
    train_cams = set(range(len(names))) - heldout
    groups = crops.groups(
        cameras=train_cams, min_views=2 if opts.mode in ("multiview", "pretrain") else 1
    )
    cut = opts.first_heldout_frame
    if cut is not None:  # held-out frames: no sample, no target, no checkpoint choice
        groups = [g for g in groups if int(crops.frame[g[0]]) < cut]
    if not groups:
        raise ValueError(
            f"no training samples: no (frame, person) seen by >= 2 training cameras "
            f"(held out: {sorted(opts.heldout_cameras)}; frames from {cut})"
        )
    used = torch.cat(groups)
    trained_on = {
        "scene": opts.scene,
        "cameras": [names[c] for c in sorted(set(crops.camera[used].tolist()))],
        "frames": [int(crops.frame[used].min()), int(crops.frame[used].max())],
        "crops": int(len(used)),
        "crop_store": opts.crop_store,
    }
    pose_crops = crops if val_crops is None else val_crops
    has_truth = "joints_world" in pose_crops.truth
    truth_rows = (
        torch.nonzero(pose_crops.truth["has_truth"])[:, 0]
        if "has_truth" in pose_crops.truth
        else torch.arange(len(pose_crops))
        if has_truth
        else torch.zeros(0, dtype=torch.long)
    )
    if val_crops is None and cut is not None:  # validation never sees the held-out frames
        truth_rows = truth_rows[pose_crops.frame[truth_rows] < cut]
    if len(truth_rows):
        gen = torch.Generator().manual_seed(1)
        truth_rows = truth_rows[
            torch.randperm(len(truth_rows), generator=gen)[: opts.val_pose_crops]
        ]
    # novel views into the held-out cameras, in training frames only: watched, never chosen on
    pairs = (
        novel_view_pairs(
            crops, heldout, max_pairs=opts.val_pairs, frames=None if cut is None else (0, cut)
        )
        if heldout
        else None
    )
    single = torch.cat(groups)  # rows usable as single-view supervised samples

    if opts.mode in ("multiview", "pretrain"):

        def sample(gen, bs):
            batch = sample_multiview(
                crops, groups, gen, bs, opts.num_targets, opts.render_size,
                landmark_dropout=opts.landmark_dropout,
            )  # fmt: skip
            return batch if rehearsal is None else RehearsedBatch(batch, rehearsal.draw(gen))

        step = (
            (lambda m, b: multiview_step(m, b, task))
            if opts.mode == "multiview"
            else (lambda m, b: _pretrain_step(m, b, task, crops))
        )
        if rehearsal is not None:
            step = _rehearsing(step, rehearsal)
    else:
        if "joints2d" not in crops.truth:
            raise ValueError(f"mode '{opts.mode}' needs truth joints on the crops")

        def sample(gen, bs):
            batch = supervised_batch(
                crops, single[torch.randint(len(single), (bs,), generator=gen)], task.world_up
            )
            return batch if opts.augment is None else jitter_batch(batch, opts.augment, gen)

        task.supervision = opts.mode

        def step(m, b):
            return supervised_step(m, b, task)

    def validate(m) -> dict:
        pose = pose_metrics(m, task, pose_crops, truth_rows) if len(truth_rows) else None
        metrics = {} if pose is None else pose.to_dict()
        if pairs is not None and len(pairs.inputs):
            views = novel_view_metrics(m, task, crops, pairs, opts.render_size)
            metrics.update({} if views is None else views.to_dict())
        return metrics

    def extra() -> dict:
        return {
            "format": "gst-capture/checkpoint",
            "version": 1,
            "config": config_to_dict(model.cfg),
            "body_model": body_spec,
            "vertex_ids": torch.as_tensor(vertex_ids, dtype=torch.long),
            "group_index": torch.as_tensor(group_index, dtype=torch.long),
            "extra": {
                "mode": opts.mode,
                "heldout_cameras": list(opts.heldout_cameras),
                "first_heldout_frame": -1 if cut is None else int(cut),
                "trained_on": trained_on,  # read by gst.track (the Parquet's gst.model)
            },
        }

    def resume_check(ckpt: dict) -> str | None:
        """Why last.pt is not this run's (None when it is): weights that trained on cameras or
        frames this run holds out (a resume continued them silently, and the checkpoint then
        recorded this run's held-out data), another mode, or another Gaussian layout."""
        had, now = ckpt.get("extra"), extra()["extra"]
        had = had if isinstance(had, dict) else {}
        for key, what in (
            ("heldout_cameras", "held-out cameras"),
            ("first_heldout_frame", "first held-out frame"),
            ("mode", "mode"),
        ):
            if had.get(key) != now[key]:
                return f"it was trained with {what} {had.get(key)!r}, this run has {now[key]!r}"
        for key, layout in (("vertex_ids", vertex_ids), ("group_index", group_index)):
            saved = ckpt.get(key)
            mine = torch.as_tensor(np.asarray(layout), dtype=torch.long)
            if not isinstance(saved, torch.Tensor) or not torch.equal(saved.long(), mine):
                return f"its Gaussians sit on other body vertices ({key} differ)"
        return None

    # The kept checkpoint is the last one, unless a validation set of its own was given
    # (`val_crops`: the pretraining's unseen world, chosen on by MPJPE). Choosing on the held-out
    # cameras (even in training frames) would make the novel-view scores of those cameras a
    # validation result, and choosing on a scene's truth would use its 3D labels: both are
    # only watched (log.csv), never used to choose.
    best_key = "mpjpe_mm" if val_crops is not None and len(truth_rows) else None
    trainer = Trainer(
        model,
        step,
        sample,
        cfg,
        out_dir,
        val_fn=validate,
        best_key=best_key,
        best_mode="min",
        progress=progress,
        checkpoint_extra=extra,
        param_groups=None
        if opts.body_lr is None
        else gaussian_parameter_groups(model, cfg.lr, opts.body_lr),
        resume_check=resume_check,
    )
    model.eval()
    before = validate(model)
    model.train()
    if resume:
        trainer.resume()
    run = trainer.fit()
    if after_from == "best":
        model.load_state_dict(load_checkpoint(trainer.best_path).model)
    model.eval()
    after = validate(model)
    return FitSummary(
        **run.to_dict(),
        before=before,
        after=after,
        train_groups=len(groups),
        heldout=list(opts.heldout_cameras),
    )


def make_task(
    body: BodyModel,
    vertex_ids,
    cfg: GSTConfig,
    crop_size: int,
    weights: LossWeights,
    lpips=None,
    supervision: str = "multiview",
    world_up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    appearance_on_teacher: bool = False,
    keypoint_markers: bool = True,
) -> GSTTask:
    """The training task. `keypoint_markers`: the keypoint term compares the landmarks with
    the virtual markers of gst.body.markers on the predicted body (False: with its joints)."""
    markers = None
    if keypoint_markers and weights.keypoints > 0:
        from gst.body.markers import MarkerModel

        markers = MarkerModel.load()
    return GSTTask(
        body=body,
        vertex_ids=torch.as_tensor(vertex_ids, dtype=torch.long),
        crop_size=crop_size,
        image_size=cfg.image_size,
        weights=weights,
        lpips=lpips,
        supervision=supervision,
        world_up=tuple(float(v) for v in world_up),
        appearance_on_teacher=appearance_on_teacher,
        markers=markers,
    )
