"""train: GST multi-view training on the scene's own crops, with no 3D labels.

Library: `gst.train.scene_training.train_scene` (docs/training.md). Starts from
`models/pretrain.pt` (or an HMR2 checkpoint with the `huge` preset), renders each prediction
into the other views of the same person and compares with what those cameras saw; with
`distill` the rig's fused bodies (`gst.lift.teacher.RigTeacher`, refitted without held-out
data) are pseudo-3D targets; with `rehearsal` the render-free landmark prior is rehearsed
beside every step (`gst.lift.rehearsal.PriorRehearsal`). Held-out cameras and frames are never
trained on. Writes `models/gst.pt`, `models/example.ply` (one predicted splat) and
`reports/train/`.
"""

from __future__ import annotations

from gst.lift.rehearsal import PriorRehearsal
from gst.lift.teacher import RigTeacher
from gst.train.scene_training import TrainOutputs, TrainSettings, train_scene
from pipeline.stage import READINGS, Stage, StageContext

CROP_STORES = {"extract": "crops/crops.h5", "bodycrops": "bodycrops/crops.h5"}


def run(ctx: StageContext) -> None:
    crops = ctx.path(CROP_STORES[ctx.params.crops])
    if not crops.is_file():
        raise FileNotFoundError(
            f"{crops} does not exist: train.crops is '{ctx.params.crops}'; run "
            f"`python -m pipeline run {'extract' if ctx.params.crops == 'extract' else 'fuse'}`"
        )
    outputs = TrainOutputs(
        model=ctx.out("models/gst.pt"),
        example_ply=ctx.out("models/example.ply"),
        reports=ctx.out("reports/train"),
        run_dir=ctx.out("models/train_run"),
    )
    train_scene(
        ctx.params,
        crops,
        ctx.path("models/pretrain.pt"),
        outputs,
        synth_dir=ctx.path("synth") if ctx.scene.is_synthetic else None,
        teacher=RigTeacher(ctx.path("fused/bodies.parquet"), crops, ctx.rig(), ctx.path(READINGS))
        if ctx.params.distill
        else None,
        scene=ctx.scene_name,
        progress=ctx.progress,
        rehearse=PriorRehearsal,
        world_up=ctx.rig().up,
    )


STAGE = Stage(
    name="train",
    run=run,
    params_model=TrainSettings,
    resumable=True,
    outputs=lambda ctx: ["models/gst.pt", "models/example.ply", "reports/train"],
    help="GST multi-view training (no 3D labels) from the pretrained model",
)
