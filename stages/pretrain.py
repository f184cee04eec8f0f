"""pretrain: pretraining on synthetic people, our stand-in for HMR2's 3D-labelled start.

Library: `gst.lift.recipe.pretrain` (docs/training.md, docs/landmark_prior.md). Mode `lift`
(default): the landmark path learns to lift BlazePose landmarks without rendering, then a short
rendered phase on a few synthetic worlds teaches the image path and the Gaussian head to work
with it; modes `3d` / `pretrain`: the image-only network on rendered worlds. One more world,
never trained on, validates. With `reuse: PATH` an existing GST checkpoint is used as it is.
Writes `models/pretrain.pt` and `reports/pretrain/`.
"""

from __future__ import annotations

from gst.lift.recipe import pretrain
from gst.train.pretrain import PretrainConfig
from pipeline.stage import Stage, StageContext


def run(ctx: StageContext) -> None:
    pretrain(
        ctx.params,
        ctx.staging,
        ctx.out("models/pretrain.pt"),
        ctx.out("reports/pretrain"),
        map_fn=ctx.executor.map if ctx.executor is not None else None,
        progress=ctx.progress,
    )


STAGE = Stage(
    name="pretrain",
    run=run,
    params_model=PretrainConfig,
    resumable=True,
    reads_scene=False,
    inputs=lambda ctx: [ctx.params.reuse] if ctx.params.reuse is not None else [],
    outputs=lambda ctx: ["models/pretrain.pt", "reports/pretrain"],
    help="supervised pretraining on separate synthetic worlds (stand-in for HMR2 weights)",
)
