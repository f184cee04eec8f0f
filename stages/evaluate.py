"""evaluate: score the trained GST model (and the pretrained start) against the scene's truth.

Pose (MPJPE, PA-MPJPE, vertex errors), novel views in held-out cameras (PSNR, SSIM, LPIPS, full
crop and SHERF box), breakdowns per camera, motion and body part, and a side-by-side image.
Only scenes with truth (synthetic ones) apply; on others the stage is skipped with a log line.
Writes `reports/evaluate/` (docs/evaluate.md).
"""

from __future__ import annotations

from pathlib import Path

import torch

from gst.body import load_body_model
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.report import write_report
from gst.eval.truth import attach_scene_truth
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.train.losses import LossWeights
from gst.train.recipe import make_task
from gst.train.views import load_cropset
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
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
    return network_from_checkpoint(ckpt).eval(), ckpt, body_cache[spec]


def run(ctx: StageContext) -> None:
    p = ctx.params
    if p.threads:
        torch.set_num_threads(p.threads)
    synth = ctx.path("synth")
    out = ctx.out("reports/evaluate")
    crops, boxes = load_cropset(ctx.path("crops/crops.h5"))
    truth = attach_scene_truth(crops, boxes, synth)
    matched = int(crops.truth["has_truth"].sum())
    ctx.log.info("evaluate: truth matched for %d of %d crops", matched, len(crops))
    heldout = p.heldout_cameras if p.heldout_cameras is not None else crops.camera_names[-1:]
    lpips = load_lpips() if p.lpips else None
    cfg = EvalConfig(
        heldout_cameras=tuple(heldout), render_size=p.render_size, max_groups=p.max_groups
    )
    bodies: dict = {}
    models = {"pretrained": ctx.path("models/pretrain.pt")} if p.compare_pretrained else {}
    models["gst"] = ctx.path("models/gst.pt")
    results, meta_models = {}, {}
    vertices = None
    for name, path in models.items():
        net, ckpt, body = _model(path, bodies)
        if vertices is None and ckpt["body_model"] == truth.body_model:
            vertices = truth.vertices(body)
        elif vertices is None:
            ctx.log.info(
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
        meta_models[name] = f"{path.relative_to(ctx.workspace)}, preset {net.cfg.name}"
        s = results[name].summary
        ctx.log.info(
            "evaluate %s: MPJPE %.1f mm, PA-MPJPE %.1f mm, held-out PSNR %s dB (%.0f s)",
            name,
            s["pose"]["overall"]["mpjpe_mm"],
            s["pose"]["overall"]["pa_mpjpe_mm"],
            s.get("novel_view", {}).get("heldout", {}).get("psnr"),
            results[name].seconds,
        )
    meta = {
        "scene": ctx.scene_name,
        "models": meta_models,
        "crops": len(crops),
        "crops_with_truth": matched,
        "note": "The frames evaluated here are the frames `train` trained on (self-supervised, no labels, "
        "held-out cameras never used); for a split by frames see benchmarks/bench_paper_tables.py.",
    }
    write_report(out, results, crops, meta, truth.motion)


def _applies(scene) -> bool:
    return scene.is_synthetic


STAGE = Stage(
    name="evaluate",
    run=run,
    params_model=Params,
    applies=_applies,
    outputs=lambda ctx: ["reports/evaluate"],
    help="pose and novel-view metrics against the synthetic truth (skipped on scenes without truth)",
)
