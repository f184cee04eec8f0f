"""pretrain: supervised pretraining on synthetic people, our stand-in for HMR2's 3D-labelled start.

Library: `gst.train.pretrain.pretrain` (docs/training.md). It renders a corpus of small
synthetic worlds, trains with 3D supervision, then briefly with the multi-view image terms so
the Gaussian head learns to render; one more world, never trained on, validates. With
`reuse: PATH` an existing GST checkpoint is used as it is. Writes `models/pretrain.pt` and
`reports/pretrain/`.
"""

from __future__ import annotations

from gst.train.pretrain import PretrainConfig, pretrain
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
    inputs=lambda ctx: [ctx.params.reuse] if ctx.params.reuse is not None else [],
    outputs=lambda ctx: ["models/pretrain.pt", "reports/pretrain"],
    help="supervised pretraining on separate synthetic worlds (stand-in for HMR2 weights)",
)
