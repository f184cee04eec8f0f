"""Score trained GST models (and the pretrained start) on a scene's crops.

Single-image pose (MPJPE, PA-MPJPE, vertex errors) of every crop, each from its own image and
landmarks, against the reference: the synthetic truth, or on a real scene the rig's fused bodies
(`fused/bodies.parquet`: the numbers then measure agreement with the rig, not error); novel
views in held-out cameras (PSNR, SSIM, LPIPS, full crop and SHERF box, silhouette IoU);
breakdowns per camera, motion and body part; a side-by-side image. By default the headline
scores the frames held out in time that `train` never saw (the trained checkpoint records
them), the pose of all frames is given beside it. Writes `reports/evaluate/` (docs/evaluate.md).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, PositiveInt, model_validator

from gst.eval.evaluate import EvalConfig, EvalResult, evaluate_model, truth_rows
from gst.eval.evaluator import evaluate_pose
from gst.eval.report import figure_text, write_report
from gst.eval.split import check_unseen
from gst.eval.summary import pose_summary
from gst.fuse.tables import read_fused_bodies
from gst.metrics.image import SSIM_WINDOW
from gst.metrics.lpips import load_lpips
from gst.metrics.lpips_weights import BACKBONES
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.model.inference import own_body
from gst.train.keypoints import store_landmarks
from gst.train.losses import LossWeights
from gst.train.recipe import make_task
from gst.train.scene_truth import attach_scene_truth
from gst.train.views import heldout_frame_start, load_cropset

log = logging.getLogger("gst.eval")


class EvaluateSettings(BaseModel):
    """Settings of the evaluation (the `evaluate` stage's parameters)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    heldout_cameras: list[str] | None = None  # default: the trained model's (train's default)
    # Which frames the headline scores: "heldout" = those `train` held out in time (recorded
    # in models/gst.pt; else the last `heldout_frames` share), "all" = every frame
    frames: Literal["heldout", "all"] = "heldout"
    heldout_frames: float = Field(
        0.25, gt=0, lt=1
    )  # only for checkpoints that do not record their held-out frames
    # Feed each crop's landmarks to models with landmark tokens (the store's, else BlazePose)
    landmarks: bool = True
    render_size: PositiveInt = 128  # novel views are rendered and scored at this size
    max_groups: PositiveInt | None = (
        None  # cap on (frame, person) groups for novel views (None: all)
    )
    compare_pretrained: bool = True  # also evaluate models/pretrain.pt, side by side
    lpips: bool = True  # LPIPS of the novel views (needs the fetched weights)
    threads: PositiveInt | None = None  # torch CPU threads (default: torch's choice)

    @model_validator(mode="after")
    def _scorable_size(self) -> EvaluateSettings:
        # SSIM's window and, with `lpips`, AlexNet's receptive field: a smaller render failed
        # after the whole pose scoring had run
        lpips_min = BACKBONES["alex"].min_size if self.lpips else 0
        need = max(SSIM_WINDOW, lpips_min)
        if self.render_size < need:
            why = f"LPIPS (AlexNet) needs {lpips_min}; " if self.lpips else ""
            raise ValueError(
                f"render_size {self.render_size} is too small to score: at least {need} px "
                f"({why}SSIM's window is {SSIM_WINDOW}; lpips: false allows {SSIM_WINDOW})"
            )
        return self


def _model(path: Path, body_cache: dict):
    ckpt = load_checkpoint(path)
    spec = ckpt.body_model
    if spec not in body_cache:  # a body that moved away: an error naming the checkpoint
        body_cache[spec] = own_body(ckpt, path)
    return network_from_checkpoint(ckpt, path).eval(), ckpt, body_cache[spec]


def _heldout_setup(
    p: EvaluateSettings, models: dict[str, Path], crops
) -> tuple[list, int | None, str | None]:
    """Held-out cameras and first held-out frame: the settings', else what the trained model
    (`gst`, else the last one) recorded, else train's defaults; and the crop store it trained
    on, as it recorded it."""
    extra = load_checkpoint(models.get("gst", list(models.values())[-1])).extra
    cams = p.heldout_cameras
    if cams is None:
        # a model trained without held-out cameras records [] (none held out: no camera's
        # scores are novel views); only a model that records nothing falls back to the last
        cams = extra.get("heldout_cameras")
        if cams is None:
            cams = crops.camera_names[-1:]
    cut = extra.get("first_heldout_frame")
    if cut is None:
        cut = heldout_frame_start(crops.frame, p.heldout_frames)
    cut = None if cut is None or cut < 0 else int(cut)
    if "gst" in models:
        check_unseen(extra, cams, cut, models["gst"])
    trained = extra.get("trained_on") if isinstance(extra, dict) else None
    store = trained.get("crop_store") if isinstance(trained, dict) else None
    return list(cams), cut, store


def fused_reference(crops, bodies_parquet: Path) -> None:
    """On a scene without truth, the rig's fused bodies stand in for it: `crops.truth` gets
    joints_world and has_truth (a fused body of the crop's person and frame, seen by >= 2
    cameras), so the evaluator measures single-image agreement with the rig."""
    bodies = read_fused_bodies(bodies_parquet)
    index = {
        (int(f), int(q)): i
        for i, (f, q) in enumerate(zip(bodies.frame, bodies.person_id, strict=True))
    }
    row = np.array(
        [index.get((int(f), int(q)), -1) for f, q in zip(crops.frame, crops.person, strict=True)]
    )
    ok = row >= 0
    ok[ok] &= bodies.observed[row[ok]] & ~bodies.single_view[row[ok]]
    joints = np.zeros((len(crops), 24, 3), np.float32)
    joints[ok] = bodies.joints[row[ok]]
    crops.truth.update(has_truth=torch.from_numpy(ok), joints_world=torch.from_numpy(joints))


def evaluate_scene(
    p: EvaluateSettings,
    crops_h5: Path,
    synth: Path | None,
    models: dict[str, Path],
    out: Path,
    *,
    fused: Path | None = None,
    scene: str = "scene",
    workspace: Path | None = None,
    world_up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> dict[str, EvalResult]:
    """Evaluate each model of `models` (name -> GST checkpoint; `compare_pretrained` decides if
    the caller includes the pretrained one) on the scene's crops against its truth (`synth`),
    or, without truth, against the rig's fused bodies (`fused`), and write the report into
    `out`; returns the results by model name. Paths in the report are shown relative to
    `workspace`. `world_up`: the rig's up axis (read by gravity-aware networks)."""
    if p.threads:
        torch.set_num_threads(p.threads)
    crops, boxes = load_cropset(crops_h5)
    truth = None
    if synth is not None:
        truth = attach_scene_truth(crops, boxes, synth)
        reference = "synthetic truth"
    elif fused is not None:
        fused_reference(crops, fused)
        reference = "the rig's fused bodies (agreement, not error)"
    else:
        raise ValueError("evaluate needs the scene's truth or the fuse stage's bodies")
    matched = int(crops.truth["has_truth"].sum())
    log.info("evaluate: a reference (%s) for %d of %d crops", reference, matched, len(crops))
    heldout, cut, crop_store = _heldout_setup(p, models, crops)
    frames = None
    if p.frames == "heldout" and cut is not None:
        frames = (cut, int(crops.frame.max()) + 1)
    lpips = load_lpips() if p.lpips else None
    cfg = EvalConfig(
        heldout_cameras=tuple(heldout),
        render_size=p.render_size,
        max_groups=p.max_groups,
        frames=frames,
    )
    bodies: dict = {}
    results: dict[str, EvalResult] = {}
    meta_models: dict[str, str] = {}
    vertices = None
    for name, path in models.items():
        net, ckpt, body = _model(path, bodies)
        if p.landmarks and net.landmark_encoder is not None and crops.landmarks is None:
            # every row is scored as a single image: landmarks projected from the rig are
            # replaced by the model's own reading (store_landmarks)
            every = np.ones(len(crops), bool)
            crops.landmarks, source = store_landmarks(crops_h5, crops.images, reread=every)
            log.info("evaluate: landmarks from %s", source)
        # vertex errors only for a model whose body is the scene's (the meshes are posed once)
        same_body = truth is not None and ckpt.body_model == truth.body_model
        if same_body and vertices is None:
            vertices = truth.vertices(body)
        task = make_task(
            body,
            ckpt.vertex_ids,
            net.cfg,
            crops.crop_size,
            LossWeights(lpips=0.0),
            world_up=world_up,
        )
        landmarks = crops.landmarks
        if not p.landmarks:
            crops.landmarks = None
        results[name] = evaluate_model(
            net,
            task,
            crops,
            cfg,
            joint_names=truth.joint_names if truth is not None else body.joint_names,
            lpips=lpips,
            scene_vertices=vertices if same_body else None,
            motions=truth.motion if truth is not None else None,
        )
        if frames is not None:  # every frame too (pose only): how much the held-out ones differ
            every = evaluate_pose(
                net, task, crops, truth_rows(crops), vertices if same_body else None
            )
            results[name].summary = replace(results[name].summary, pose_all_frames=pose_summary(
                every, crops.camera_names, np.full(len(every.rows), "all", dtype=object),
                truth.joint_names if truth is not None else body.joint_names,
            ).overall)  # fmt: skip
        crops.landmarks = landmarks
        shown = path.relative_to(workspace) if workspace is not None else path
        uses = (
            "with landmarks" if net.landmark_encoder is not None and p.landmarks else "image only"
        )
        meta_models[name] = f"{shown}, preset {net.cfg.name}, {uses}"
        s = results[name].summary
        held = s.novel_view.heldout if s.novel_view else {}
        log.info(
            "evaluate %s: MPJPE %s mm, PA-MPJPE %s mm (%s), %s (%.0f s)",
            name,
            figure_text(s.pose.overall["mpjpe_mm"]),
            figure_text(s.pose.overall["pa_mpjpe_mm"]),
            "held-out frames" if frames else "all frames",
            f"held-out PSNR {held.get('psnr')} dB, IoU {held.get('silhouette_iou')}"
            if held.get("n")
            else f"no held-out view scored (no scored person seen in {list(heldout) or 'none'})",
            results[name].seconds,
        )
    meta = {
        "scene": scene,
        "models": meta_models,
        "reference": reference,
        "crops": len(crops),
        "crops_with_reference": matched,
        "frames": list(frames) if frames else "all",
        "heldout_cameras": heldout,
        "note": (
            f"Headline: frames {frames[0]}-{frames[1] - 1}, held out in time (this run's "
            "training never saw them: no sample, no target, no checkpoint choice; some project "
            "defaults were chosen on the demo's and the lab's held-out numbers, docs/training.md "
            "'Held-out data and the defaults') and, for novel views, the held-out cameras; "
            "`pose_all_frames` in summary.json scores every frame."
            + (
                " Not clean: the model trained on `bodycrops`, crops cut from bodies fitted on "
                "every camera and frame, the held-out ones included."
                if crop_store == "bodycrops"
                else ""
            )
            if frames
            else "Every frame is scored, including those `train` trained on (self-supervised, no "
            "labels; held-out cameras never used)."
        )
        + f" Reference: {reference}.",
    }
    write_report(out, results, crops, meta, truth.motion if truth is not None else None)
    return results
