"""The `pretrain` stage's recipe (`pretrain`), and its mode `lift`: render-free lifting, then a
short rendered phase. Modes `3d` / `pretrain` (the image-only network) are
`gst.train.pretrain.pretrain_images`; `reuse` copies a checkpoint.

1. `lift_phase`: a network with landmark tokens learns the landmark -> body path in its
   landmark-only mode on simulated BlazePose detections of sampled bodies (`gst.lift`), no
   image rendered; the image path and the Gaussian head are untouched.
2. `rendered_phase`: the image path and the Gaussian head learn to work with the landmark
   tokens, on crops of a few rendered worlds with the landmarks BlazePose finds in them
   (`attach_landmarks`): 3D terms plus the multi-view image terms (`fit_gst` mode
   `pretrain`), the Gaussian head at its own rate, the ViT and the image cross-attention gently,
   the pose path frozen behind a closed image gate (`silence_image_path`): a crop with
   landmarks keeps the lifting path's pose exactly (measured: training the pose path on a few
   rendered worlds made it transfer worse, docs/landmark_prior.md), and scene training opens
   the gate as far as the image helps.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
from torch import nn

from gst.atomic import atomic_torch_save
from gst.body import BodyModel, load_body_model
from gst.detect.crops import detect_crop_landmarks
from gst.device import resolve_device
from gst.lift.errors import LANDMARK_SETS
from gst.lift.pretrain import LiftPretrainConfig, LiftPretrainResult, pretrain_landmark_path
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import keep_model
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset
from gst.model.refine import DEFAULT_ROUNDS
from gst.records import Record
from gst.train.pretrain import (
    LIFT_CROP_SIZE,
    CorpusSummary,
    ImagePretrainSummary,
    PretrainConfig,
    ReusedCheckpoint,
    corpus_crops,
    corpus_summary,
    pretrain_images,
    render_corpus,
    reuse_checkpoint,
    world_specs,
)
from gst.train.recipe import FitOptions, FitSummary, build_network, fit_gst, make_task
from gst.train.steps import GSTTask
from gst.train.teacher_render import truth_targets
from gst.train.trainer import TrainConfig
from gst.train.views import CropSet

log = logging.getLogger("gst.train")

__all__ = [
    "pretrain",
    "LiftPretrainSummary",
    "LiftTimes",
    "lift_network",
    "lift_phase",
    "silence_image_path",
    "attach_landmarks",
    "rendered_phase",
]


def lift_network(
    preset: str,
    body: BodyModel,
    landmarks: str = "all",
    point_tokens: bool = False,
    seed: int = 0,
    refine: int = DEFAULT_ROUNDS,
) -> tuple[GSTNetwork, object, object]:
    """A fresh network of `preset` with landmark tokens for the landmark set `landmarks`, which
    reads the camera's up direction where the camera is calibrated, with `refine` rounds of
    reprojection feedback (gst.model.refine; 0: none)."""
    cfg = get_preset(
        preset,
        landmark_tokens=True,
        num_landmarks=len(LANDMARK_SETS[landmarks]),
        landmark_point_tokens=point_tokens,
        landmark_gravity=True,
        landmark_refine=refine,
    )
    return build_network(cfg, body, seed)


def lift_phase(
    net: GSTNetwork,
    body: BodyModel,
    steps: int,
    batch_size: int,
    lr: float,
    seed: int = 0,
    threads: int | None = None,
) -> LiftPretrainResult:
    """The render-free lifting phase (training throughput in the result: samples per second) on
    `threads` torch threads (None: the cores the background sampler leaves)."""
    cfg = LiftPretrainConfig(
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        seed=seed,
        warmup_steps=min(100, max(1, steps // 10)),
        threads=threads,
    )
    res = pretrain_landmark_path(net, body, cfg, log=log.info)
    log.info(
        "pretrain (lift): %d steps x %d samples in %.0f s: %.0f samples/s (sampler alone %.0f/s), "
        "simulated crops %.0f mm",
        steps,
        batch_size,
        res.seconds,
        res.samples_per_s,
        res.sampler_samples_per_s,
        res.train_mpjpe_mm,
    )
    return res


def silence_image_path(net: GSTNetwork) -> None:
    """Close the SMPL token's image gate (`TokenDecoder.smpl_image_gate` = 0): a crop with
    landmarks then gets the lifting path's pose exactly, whatever the image path learns for the
    Gaussian tokens; scene training opens it as far as the image helps."""
    with torch.no_grad():
        net.smpl_head.transformer.smpl_image_gate.zero_()


def image_path_parameters(net: GSTNetwork) -> list[nn.Parameter]:
    """What the rendered phase trains besides the Gaussian head: the ViT and the decoder's
    image cross-attention (through which the Gaussian tokens see the crop)."""
    cross = [
        p for layer in net.smpl_head.transformer.transformer.layers for p in layer[1].parameters()
    ]
    return list(net.backbone.parameters()) + cross


def attach_landmarks(crops: CropSet, progress=None) -> None:
    """BlazePose on every crop (RGB), as the pipeline sees them: `crops.landmarks`."""
    found = detect_crop_landmarks(crops.images.numpy(), rgb=True, progress=progress)
    crops.landmarks = torch.from_numpy(found.with_confidence())


def rendered_phase(
    net: GSTNetwork,
    task: GSTTask,
    crops: CropSet,
    val: CropSet | None,
    out: Path,
    *,
    steps: int,
    batch_size: int,
    gaussian_lr: float,
    body_lr: float,
    num_targets: int,
    render_size: int,
    landmark_dropout: float,
    body_spec: str,
    vertex_ids,
    group_index,
    progress=None,
    device: str = "cpu",
    amp: bool = False,
) -> FitSummary:
    """Train in place on rendered crops with their landmarks (module doc): the Gaussian head at
    `gaussian_lr`, the image path (`image_path_parameters`) at `body_lr`, the pose path frozen
    (the SMPL token's image gate stays closed); writes `out`/last.pt and log.csv; returns
    fit_gst's summary (MPJPE before and after on `val`)."""
    keep = {id(p) for p in image_path_parameters(net)} | {
        id(p) for p in net.gaussian_head.parameters()
    }
    frozen = [p for p in net.parameters() if id(p) not in keep and p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    cfg = TrainConfig(
        steps=steps,
        batch_size=batch_size,
        lr=gaussian_lr,
        warmup_steps=min(20, max(1, steps // 10)),
        val_every=steps,
        ckpt_every=25,
        log_every=5,
        device=device,
        amp=amp,
    )
    try:
        return fit_gst(
            net,
            task,
            crops,
            cfg,
            out,
            FitOptions(
                mode="pretrain",
                num_targets=num_targets,
                render_size=render_size,
                val_pose_crops=256,
                body_lr=body_lr,
                landmark_dropout=landmark_dropout,
            ),
            body_spec=body_spec,
            vertex_ids=vertex_ids,
            group_index=group_index,
            progress=progress,
            val_crops=val,
        )
    finally:
        for p in frozen:
            p.requires_grad_(True)


@dataclass(frozen=True)
class LiftTimes(Record):
    """Seconds since mode `lift` started (rounded to 0.1 s) at which each part was done."""

    lift_phase: float
    rendering_done: float
    crops_and_landmarks_done: float
    total: float


@dataclass(frozen=True)
class LiftPretrainSummary:
    """What mode `lift` returns (and writes as summary.json): the rendered phase's fit, the
    lift phase (`lift_summary`'s JSON form), the corpus and the times."""

    fit: FitSummary
    lift: dict
    corpus: CorpusSummary
    times_s: LiftTimes
    mode: str = "lift"

    def to_dict(self) -> dict:
        """summary.json: the fit's fields, then mode, lift, corpus, times_s."""
        return {
            **self.fit.to_dict(),
            "mode": self.mode,
            "lift": self.lift,
            "corpus": self.corpus.to_dict(),
            "times_s": self.times_s.to_dict(),
        }


def lift_summary(res: LiftPretrainResult) -> dict:
    d = asdict(replace(res, validation=[]))
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in d.items()}


def _lift_settings(p: PretrainConfig) -> dict:
    """What the lifting's result depends on (its kept result is reused only when they match)."""
    return {
        k: getattr(p, k)
        for k in (
            "preset", "body_model", "landmarks", "landmark_point_tokens", "landmark_refine",
            "lift_steps", "lift_batch_size", "lift_lr",
        )
    }  # fmt: skip


def _load_lifted(net: GSTNetwork, path: Path, settings: dict) -> LiftPretrainResult | None:
    """The kept lifting of an interrupted run into `net` (None: none, or of other settings)."""
    if not path.is_file():
        return None
    try:
        kept = torch.load(path, map_location="cpu", weights_only=True)
        if kept["settings"] != settings:
            log.info("pretrain (lift): %s is of other settings; lifting again", path)
            return None
        net.load_state_dict(kept["model"])
        return LiftPretrainResult(**kept["lift"])
    except Exception as exc:  # unreadable (e.g. cut short): lift again
        log.warning("pretrain (lift): cannot reuse %s (%s); lifting again", path, exc)
        return None


def _save_lifted(net: GSTNetwork, lift: LiftPretrainResult, path: Path, settings: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_torch_save({"settings": settings, "model": net.state_dict(), "lift": asdict(lift)}, path)


def _pretrain_lift(
    p: PretrainConfig, work: Path, checkpoint: Path, reports: Path, map_fn, progress
) -> LiftPretrainSummary:
    """Mode `lift` (module doc). The worlds render in the background while the landmark path
    learns without them."""
    t0 = time.perf_counter()
    specs = world_specs(p)
    body = load_body_model(p.body_model)
    net, ids, groups = lift_network(
        p.preset, body, p.landmarks, p.landmark_point_tokens, refine=p.landmark_refine
    )
    with ThreadPoolExecutor(1, thread_name_prefix="pretrain-render") as pool:
        rendering = pool.submit(render_corpus, p, work, map_fn, None)
        # A finished lifting is kept in `work` (the stage's staging, kept by an interrupted
        # run): a run killed in the renders, BlazePose or the rendered phase lifted again from
        # scratch when resumed, though the rendered phase resumes from its own last.pt.
        lifted = work / "models" / "pretrain_lift.pt"
        lift = _load_lifted(net, lifted, _lift_settings(p))
        if lift is None:
            # pretrain.threads holds here too (the loop took the cores less one whatever was set)
            lift = lift_phase(
                net, body, p.lift_steps, p.lift_batch_size, p.lift_lr, threads=p.threads
            )
            _save_lifted(net, lift, lifted, _lift_settings(p))
        else:
            log.info("pretrain (lift): resuming with the finished lifting in %s", lifted)
        t_lift = time.perf_counter() - t0
        dirs = rendering.result()
    t_render = time.perf_counter() - t0
    crops, val = corpus_crops(p, dirs, LIFT_CROP_SIZE, progress)
    attach_landmarks(crops, progress)
    attach_landmarks(val, progress)
    t_detect = time.perf_counter() - t0
    silence_image_path(net)
    lpips = load_lpips() if p.losses.lpips > 0 else None
    losses = p.losses
    if p.appearance_on_truth:
        # the truth only poses the Gaussians: its distillation terms stay off (the phase's
        # supervised terms are the pose's)
        crops.distill = truth_targets(crops)
        losses = losses.model_copy(
            update={"distill_joints": 0.0, "distill_root": 0.0, "distill_params": 0.0}
        )
    task = make_task(
        body, ids, net.cfg, crops.crop_size, losses, lpips,
        appearance_on_teacher=p.appearance_on_truth,
    )  # fmt: skip
    out = work / "models" / "pretrain_rendered"
    out.mkdir(parents=True, exist_ok=True)
    fit = rendered_phase(
        net, task, crops, val, out,
        steps=p.gaussian_steps, batch_size=p.batch_size, gaussian_lr=p.gaussian_lr,
        body_lr=p.lift_body_lr, num_targets=p.num_targets, render_size=p.render_size,
        landmark_dropout=p.landmark_dropout, body_spec=p.body_model, vertex_ids=ids,
        group_index=groups, progress=progress, device=p.device, amp=p.amp,
    )  # fmt: skip
    reports.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(out / "log.csv", reports / "log.csv")
    keep_model(out / "last.pt", checkpoint)  # the head learns to the end; the pose is watched
    summary = LiftPretrainSummary(
        fit=fit,
        lift=lift_summary(lift),
        corpus=corpus_summary(specs, crops, val),
        times_s=LiftTimes(
            lift_phase=round(t_lift, 1),
            rendering_done=round(t_render, 1),
            crops_and_landmarks_done=round(t_detect, 1),
            total=round(time.perf_counter() - t0, 1),
        ),
    )
    (reports / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2, default=float))
    log.info(
        "pretrain (lift): MPJPE on the unseen validation world %.1f mm after lifting, "
        "%.1f mm after the rendered phase; %.0f s in all",
        fit.before.get("mpjpe_mm", float("nan")),
        fit.after.get("mpjpe_mm", float("nan")),
        summary.times_s.total,
    )
    shutil.rmtree(out)
    shutil.rmtree(work / "worlds")
    lifted.unlink()
    return summary


def pretrain(
    p: PretrainConfig,
    work: Path,
    checkpoint: Path,
    reports: Path,
    *,
    map_fn=None,
    progress=None,
) -> ReusedCheckpoint | ImagePretrainSummary | LiftPretrainSummary:
    """The pretrain stage: `p.reuse` copies a checked checkpoint; mode `lift` (module doc);
    modes `3d` / `pretrain`: `gst.train.pretrain.pretrain_images`. Worlds render into
    `work/worlds` (kept by an interrupted run); writes `checkpoint` and `reports`; returns the
    summary. `map_fn` fans the world renders out (an executor's map)."""
    if p.reuse is not None:
        return reuse_checkpoint(p, checkpoint, reports)
    resolve_device(p.device)  # `device: cuda` without CUDA fails now, not after the renders
    if p.mode != "lift":
        return pretrain_images(p, work, checkpoint, reports, map_fn=map_fn, progress=progress)
    if p.threads:
        torch.set_num_threads(p.threads)
    return _pretrain_lift(p, work, checkpoint, reports, map_fn, progress)
