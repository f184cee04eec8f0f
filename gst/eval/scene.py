"""Score trained GST models (and the pretrained start) on a scene's crops against its truth.

Pose (MPJPE, PA-MPJPE, vertex errors), novel views in held-out cameras (PSNR, SSIM, LPIPS, full
crop and SHERF box), breakdowns per camera, motion and body part, and a side-by-side image.
Only scenes with truth (synthetic ones) can be scored.
Writes `reports/evaluate/` (docs/evaluate.md).
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from pydantic import BaseModel, ConfigDict

from gst.body import load_body_model
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.report import write_report
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.train.losses import LossWeights
from gst.train.recipe import make_task
from gst.train.scene_truth import attach_scene_truth
from gst.train.views import load_cropset

log = logging.getLogger("gst.eval")


class EvaluateSettings(BaseModel):
    """Settings of the evaluation (the `evaluate` stage's parameters)."""

    model_config = ConfigDict(extra="forbid")

    heldout_cameras: list[str] | None = None  # default: the rig's last camera, as in train
    render_size: int = 128  # novel views are rendered and scored at this size
    max_groups: int | None = None  # cap on (frame, person) groups for novel views (None: all)
    compare_pretrained: bool = True  # also evaluate models/pretrain.pt, side by side
    lpips: bool = True
    threads: int | None = None


def _model(path: Path, body_cache: dict):
    ckpt = load_checkpoint(path)
    spec = ckpt["body_model"]
    if spec not in body_cache:
        body_cache[spec] = load_body_model(spec)
    return network_from_checkpoint(ckpt, path).eval(), ckpt, body_cache[spec]


def evaluate_scene(
    p: EvaluateSettings,
    crops_h5: Path,
    synth: Path,
    models: dict[str, Path],
    out: Path,
    *,
    scene: str = "scene",
    workspace: Path | None = None,
) -> dict:
    """Evaluate each model of `models` (name -> GST checkpoint; `compare_pretrained` decides if
    the caller includes the pretrained one) on the scene's crops against its truth and write
    the report into `out`; returns the results by model name. Paths in the report are shown
    relative to `workspace`."""
    if p.threads:
        torch.set_num_threads(p.threads)
    crops, boxes = load_cropset(crops_h5)
    truth = attach_scene_truth(crops, boxes, synth)
    matched = int(crops.truth["has_truth"].sum())
    log.info("evaluate: truth matched for %d of %d crops", matched, len(crops))
    heldout = p.heldout_cameras if p.heldout_cameras is not None else crops.camera_names[-1:]
    lpips = load_lpips() if p.lpips else None
    cfg = EvalConfig(
        heldout_cameras=tuple(heldout), render_size=p.render_size, max_groups=p.max_groups
    )
    bodies: dict = {}
    results, meta_models = {}, {}
    vertices = None
    for name, path in models.items():
        net, ckpt, body = _model(path, bodies)
        if vertices is None and ckpt["body_model"] == truth.body_model:
            vertices = truth.vertices(body)
        elif vertices is None:
            log.info(
                "evaluate: model body '%s' differs from the scene's '%s': no vertex error, SHERF box "
                "from joints",
                ckpt["body_model"],
                truth.body_model,
            )
        task = make_task(body, ckpt["vertex_ids"], net.cfg, crops.crop_size, LossWeights(lpips=0.0))
        results[name] = evaluate_model(
            net,
            task,
            crops,
            cfg,
            joint_names=truth.joint_names,
            lpips=lpips,
            scene_vertices=vertices,
            motions=truth.motion,
        )
        shown = path.relative_to(workspace) if workspace is not None else path
        meta_models[name] = f"{shown}, preset {net.cfg.name}"
        s = results[name].summary
        log.info(
            "evaluate %s: MPJPE %.1f mm, PA-MPJPE %.1f mm, held-out PSNR %s dB (%.0f s)",
            name,
            s["pose"]["overall"]["mpjpe_mm"],
            s["pose"]["overall"]["pa_mpjpe_mm"],
            s.get("novel_view", {}).get("heldout", {}).get("psnr"),
            results[name].seconds,
        )
    meta = {
        "scene": scene,
        "models": meta_models,
        "crops": len(crops),
        "crops_with_truth": matched,
        "note": "The frames evaluated here are the frames `train` trained on (self-supervised, no labels, "
        "held-out cameras never used); for a split by frames see benchmarks/bench_paper_tables.py.",
    }
    write_report(out, results, crops, meta, truth.motion)
    return results
