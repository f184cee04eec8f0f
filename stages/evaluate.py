"""evaluate: score the trained GST model (and the pretrained start) against the scene's truth.

Library: `gst.eval.scene.evaluate_scene`. Pose (MPJPE, PA-MPJPE, vertex errors), novel views in
held-out cameras (PSNR, SSIM, LPIPS, full crop and SHERF box), breakdowns per camera, motion and
body part, and a side-by-side image. Only scenes with truth (synthetic ones) apply; the stage
is skipped elsewhere. Writes `reports/evaluate/` (docs/evaluate.md).
"""

from __future__ import annotations

from gst.eval.scene import EvaluateSettings, evaluate_scene
from pipeline.stage import Stage, StageContext


def run(ctx: StageContext) -> None:
    models = {"pretrained": ctx.path("models/pretrain.pt")} if ctx.params.compare_pretrained else {}
    models["gst"] = ctx.path("models/gst.pt")
    evaluate_scene(
        ctx.params,
        ctx.path("crops/crops.h5"),
        ctx.path("synth"),
        models,
        ctx.out("reports/evaluate"),
        scene=ctx.scene_name,
        workspace=ctx.workspace,
    )


STAGE = Stage(
    name="evaluate",
    run=run,
    params_model=EvaluateSettings,
    applies=lambda scene: scene.is_synthetic,
    outputs=lambda ctx: ["reports/evaluate"],
    help="pose and novel-view metrics against the synthetic truth (skipped on scenes without truth)",
)
