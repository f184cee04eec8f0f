"""evaluate: score the trained GST model (and the pretrained start) from single images.

Library: `gst.eval.scene.evaluate_scene`. Pose (MPJPE, PA-MPJPE, vertex errors) of every crop
from its own image and landmarks, against the synthetic truth or, on a real scene, the rig's
fused bodies (agreement with the rig); novel views in held-out cameras (PSNR, SSIM, LPIPS, full
crop and SHERF box, silhouette IoU); breakdowns per camera, motion and body part; a side-by-side
image. The headline scores the frames `train` held out in time. Writes `reports/evaluate/`
(docs/evaluate.md).
"""

from __future__ import annotations

from gst.eval.scene import EvaluateSettings, evaluate_scene
from pipeline.stage import Stage, StageContext


def run(ctx: StageContext) -> None:
    models = {"pretrained": ctx.path("models/pretrain.pt")} if ctx.params.compare_pretrained else {}
    models["gst"] = ctx.path("models/gst.pt")
    synthetic = ctx.scene.is_synthetic
    evaluate_scene(
        ctx.params,
        ctx.path("crops/crops.h5"),
        ctx.path("synth") if synthetic else None,
        models,
        ctx.out("reports/evaluate"),
        fused=None if synthetic else ctx.path("fused/bodies.parquet"),
        scene=ctx.scene_name,
        workspace=ctx.workspace,
        world_up=ctx.rig().up,
    )


STAGE = Stage(
    name="evaluate",
    run=run,
    params_model=EvaluateSettings,
    outputs=lambda ctx: ["reports/evaluate"],
    help="single-image pose and novel-view metrics (synthetic truth, or the rig's fused bodies)",
)
