"""One call that evaluates a GST model on crops with truth: pose records, novel-view records and
their summary (see `gst.eval.evaluator` for the metrics and `gst.eval.summary` for the layout)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from gst.eval.evaluator import (
    PoseRecords,
    ViewPairs,
    ViewRecords,
    evaluate_pose,
    evaluate_views,
    sherf_box_kind,
    view_pairs,
)
from gst.eval.summary import PoseSummary, ViewSummary, pose_summary, view_summary
from gst.records import Record
from gst.train.steps import GSTTask
from gst.train.views import CropSet

__all__ = [
    "EvalConfig",
    "EvalCounts",
    "EvalResult",
    "EvalSummary",
    "evaluate_model",
    "truth_rows",
]


@dataclass(frozen=True)
class EvalConfig:
    heldout_cameras: tuple[str, ...] = ()  # novel-view headline: targets in these cameras
    render_size: int = 128  # novel views are rendered and compared at this size (px)
    frames: tuple[int, int] | None = None  # evaluate frames in [lo, hi) only (a test split)
    max_groups: int | None = None  # cap on (frame, person) groups used for novel views
    with_views: bool = True  # False: pose only (no rendering)
    side_by_side_groups: int = 3  # groups whose images are kept for the side-by-side figure
    seed: int = 0


@dataclass(frozen=True)
class EvalCounts(Record):
    """What one evaluation scored: crops (pose), view pairs, render size, frames ([lo, hi) or
    None for all), held-out cameras, and the seconds it took."""

    pose_crops: int
    view_pairs: int
    render_size: int
    frames: list[int] | None
    heldout_cameras: list[str]
    seconds: float
    # the SHERF-style box of the novel views: "mesh" (the truth body's, 5 cm margin), "joints"
    # (the reference joints', 15 cm: no truth mesh, e.g. the rig's fused bodies), None (none)
    sherf_box: str | None = None


@dataclass(frozen=True)
class EvalSummary:
    """One model's evaluation summary (a model's entry in summary.json): pose, novel views
    (None when not rendered), counts, and `pose_all_frames` (the overall pose block over every
    frame, set by `gst.eval.scene` when the headline is on held-out frames only)."""

    pose: PoseSummary
    counts: EvalCounts
    novel_view: ViewSummary | None = None
    pose_all_frames: dict | None = None

    def to_dict(self) -> dict:
        """The summary.json layout: pose, novel_view (when rendered), counts, pose_all_frames
        (when set)."""
        out: dict = {"pose": self.pose.to_dict()}
        if self.novel_view is not None:
            out["novel_view"] = self.novel_view.to_dict()
        out["counts"] = self.counts.to_dict()
        if self.pose_all_frames is not None:
            out["pose_all_frames"] = self.pose_all_frames
        return out


@dataclass
class EvalResult:
    summary: EvalSummary
    pose: PoseRecords
    views: ViewRecords | None
    pairs: ViewPairs | None
    side_by_side: list[int] = field(default_factory=list)  # pair indices with kept images
    seconds: float = 0.0


def truth_rows(crops: CropSet, frames: tuple[int, int] | None = None) -> torch.Tensor:
    """Rows with truth (has_truth, or all rows when the key is absent), within `frames`."""
    keep = (
        crops.truth["has_truth"].bool().clone()
        if "has_truth" in crops.truth
        else torch.ones(len(crops), dtype=torch.bool)
    )
    if frames is not None:
        keep &= (crops.frame >= frames[0]) & (crops.frame < frames[1])
    return torch.nonzero(keep)[:, 0]


def _labels(motions: np.ndarray | None, crops: CropSet, rows: np.ndarray) -> np.ndarray:
    if motions is None or "truth_row" not in crops.truth:
        return np.full(len(rows), "all", dtype=object)
    return np.asarray(motions, dtype=object)[
        crops.truth["truth_row"][torch.as_tensor(rows)].numpy()
    ]


def evaluate_model(
    model,
    task: GSTTask,
    crops: CropSet,
    cfg: EvalConfig,
    *,
    joint_names,
    lpips=None,
    scene_vertices: torch.Tensor | None = None,
    motions: np.ndarray | None = None,
) -> EvalResult:
    """Evaluate `model` on the crops with truth (see module doc). `motions` (P,) labels the
    truth rows (SceneTruth.motion); `scene_vertices` (P, V, 3) enables vertex and SHERF box
    metrics."""
    unknown = [c for c in cfg.heldout_cameras if c not in crops.camera_names]
    if unknown:
        raise ValueError(
            f"held-out cameras {unknown} are not in the crop set (cameras: {crops.camera_names})"
        )
    t0 = time.perf_counter()
    model.eval()
    rows = truth_rows(crops, cfg.frames)
    if len(rows) == 0:
        raise ValueError(
            f"no crop with truth to evaluate (frames {cfg.frames}, {len(crops)} crops)"
        )
    pose = evaluate_pose(model, task, crops, rows, scene_vertices)
    pose_table = pose_summary(
        pose, crops.camera_names, _labels(motions, crops, pose.rows), joint_names
    )
    view_table = views = pairs = None
    kept: list[int] = []
    if cfg.with_views:
        heldout = {crops.camera_names.index(c) for c in cfg.heldout_cameras}
        pairs = view_pairs(crops, heldout, rows, cfg.max_groups, cfg.seed)
        if len(pairs.inputs):
            first_inputs = list(dict.fromkeys(pairs.inputs.tolist()))[: cfg.side_by_side_groups]
            kept = [i for i, x in enumerate(pairs.inputs.tolist()) if x in first_inputs]
            views = evaluate_views(
                model,
                task,
                crops,
                pairs,
                heldout,
                cfg.render_size,
                lpips,
                scene_vertices,
                keep_images=set(kept),
            )
            view_table = view_summary(
                views, crops.camera_names, _labels(motions, crops, views.targets)
            )
    seconds = time.perf_counter() - t0
    counts = EvalCounts(
        pose_crops=int(len(rows)),
        view_pairs=int(len(pairs.inputs)) if pairs else 0,
        render_size=cfg.render_size,
        frames=list(cfg.frames) if cfg.frames else None,
        heldout_cameras=list(cfg.heldout_cameras),
        seconds=seconds,
        sherf_box=None if views is None else sherf_box_kind(crops, scene_vertices),
    )
    summary = EvalSummary(pose=pose_table, counts=counts, novel_view=view_table)
    return EvalResult(summary, pose, views, pairs, kept, seconds)
