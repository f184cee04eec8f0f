"""Train/test splits of a crop set with truth, and short equal-budget training runs on a split.

The split is by frames (the last `test_fraction` of the frames are test) and by cameras (held-out
cameras are never trained on), so a model is scored on poses and views it never saw.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, Rehearsal, fit_gst, make_task
from gst.train.scene_truth import select_rows
from gst.train.trainer import TrainConfig
from gst.train.views import CropSet, heldout_frame_start

__all__ = ["Split", "frame_split", "check_unseen", "FinetuneConfig", "finetune"]


@dataclass(frozen=True)
class Split:
    train_rows: torch.Tensor  # crops with truth, training frames, training cameras
    test_frames: tuple[int, int]  # [lo, hi)
    heldout_cameras: tuple[str, ...]


def frame_split(
    crops: CropSet, heldout_cameras: tuple[str, ...], test_fraction: float = 0.25
) -> Split:
    """The last `test_fraction` of the frames with crops are test; training rows have truth, an
    earlier frame and a camera not held out."""
    if not 0 < test_fraction < 1:
        raise ValueError(f"test_fraction must lie in (0, 1), got {test_fraction}")
    unknown = [c for c in heldout_cameras if c not in crops.camera_names]
    if unknown:
        raise ValueError(
            f"held-out cameras {unknown} are not in the crop set (cameras: {crops.camera_names})"
        )
    frames = torch.unique(crops.frame)
    if len(frames) < 2:
        raise ValueError(f"a frame split needs crops from >= 2 frames, got {len(frames)}")
    first_test = heldout_frame_start(crops.frame, test_fraction)
    held = torch.tensor([crops.camera_names.index(c) for c in heldout_cameras], dtype=torch.long)
    has = (
        crops.truth["has_truth"].bool()
        if "has_truth" in crops.truth
        else torch.ones(len(crops), dtype=torch.bool)
    )
    keep = has & (crops.frame < first_test) & ~torch.isin(crops.camera, held)
    return Split(
        torch.nonzero(keep)[:, 0], (first_test, int(frames[-1]) + 1), tuple(heldout_cameras)
    )


def check_unseen(
    extra: dict, heldout_cameras, first_test_frame: int | None, model: str | Path
) -> None:
    """Refuse to score a scene's trained model (`extra`: its checkpoint's record,
    `trained_on` and `first_heldout_frame`) on held-out cameras or test frames it trained on:
    its novel-view and test-frame scores would be training scores. A split other than the
    training's (an `evaluate.heldout_cameras` or a bench `test_fraction` of one's own) is
    where that happens. Checkpoints that record nothing are not checked."""
    trained = extra.get("trained_on") if isinstance(extra, dict) else None
    if not isinstance(trained, dict) or not trained.get("cameras"):
        return
    problems = []
    seen = sorted(set(trained["cameras"]) & set(heldout_cameras))
    if seen:
        problems.append(f"held-out camera(s) {seen} are among the cameras it trained on")
    frames = trained.get("frames")
    if first_test_frame is not None and frames and first_test_frame <= int(frames[1]):
        problems.append(
            f"test frames from {first_test_frame} include frames it trained on (up to "
            f"{int(frames[1])}; its own held-out frames start at "
            f"{extra.get('first_heldout_frame')})"
        )
    if problems:
        raise ValueError(
            f"{model}: " + "; ".join(problems) + ". Score it on the split it was trained with "
            "(the settings' defaults read it from the checkpoint), or train it again"
        )


@dataclass(frozen=True)
class FinetuneConfig:
    mode: str  # fit_gst mode: multiview | pretrain | 2d | 3d
    steps: int
    batch_size: int = 8
    lr: float = 1e-4
    num_targets: int = 4
    render_size: int = 64
    weights: LossWeights = field(default_factory=LossWeights)
    body_lr: float | None = None  # backbone + SMPL head rate (None: `lr` for everything)
    landmark_dropout: float = 0.0  # multi-view samples trained without their landmarks
    # the Gaussians posed on the rig teacher's body, not the network's (the train stage's
    # default with distillation: TrainSettings.appearance_on_teacher)
    appearance_on_teacher: bool = False


def finetune(
    net,
    body,
    vertex_ids,
    group_index,
    crops: CropSet,
    split: Split,
    cfg: FinetuneConfig,
    *,
    body_spec: str,
    lpips=None,
    run_dir: Path | None = None,
    rehearsal: Rehearsal | None = None,
) -> float:
    """Train `net` in place on the split's training rows for exactly `cfg.steps` steps (no
    validation inside the loop, the final weights are kept). Returns the training seconds.
    `rehearsal`: rehearsed beside every multi-view step (gst.train.recipe.Rehearsal)."""
    train = select_rows(crops, split.train_rows)
    task = make_task(
        body,
        vertex_ids,
        net.cfg,
        crops.crop_size,
        cfg.weights,
        lpips if cfg.weights.lpips > 0 else None,
        appearance_on_teacher=cfg.appearance_on_teacher,
    )
    tc = TrainConfig(
        steps=cfg.steps,
        batch_size=cfg.batch_size,
        lr=cfg.lr,
        warmup_steps=min(30, cfg.steps // 10),
        val_every=10**9,
        ckpt_every=10**9,
        log_every=max(1, cfg.steps // 10),
    )
    opts = FitOptions(
        mode=cfg.mode,
        num_targets=cfg.num_targets,
        render_size=cfg.render_size,
        val_pose_crops=0,
        body_lr=cfg.body_lr,
        landmark_dropout=cfg.landmark_dropout if train.landmarks is not None else 0.0,
    )
    with tempfile.TemporaryDirectory(dir=run_dir) as tmp:
        t0 = time.perf_counter()
        fit_gst(
            net,
            task,
            train,
            tc,
            Path(tmp),
            opts,
            body_spec=body_spec,
            vertex_ids=vertex_ids,
            group_index=group_index,
            resume=False,
            rehearsal=rehearsal,
        )
        seconds = time.perf_counter() - t0
    net.eval()
    return seconds
