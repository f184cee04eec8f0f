"""bench: run time against error for model variants, in one run, on the scene's crops with truth.

Library: `gst.eval.bench_scene.bench_scene`. Sweeps backbone preset, input size and Gaussian
count; every variant is trained with the same short budget on the training split, timed
pose-only and full (median of repeats), and scored on the test split. Writes `reports/bench/`
(table.md, table.csv, pareto.png; docs/evaluate.md).
"""

from __future__ import annotations

from gst.eval.bench_scene import BenchSettings, bench_scene
from pipeline.stage import Stage, StageContext


def run(ctx: StageContext) -> None:
    bench_scene(
        ctx.params,
        ctx.path("crops/crops.h5"),
        ctx.path("synth"),
        ctx.path("models/pretrain.pt"),
        ctx.out("reports/bench"),
        scene=ctx.scene_name,
        workspace=ctx.workspace,
    )


def _trained_model(ctx: StageContext) -> list:
    """The scene's trained model, scored when there is one: an input, so a retrained model
    makes the bench stale (train is not among its needs: the bench runs without one)."""
    model = ctx.path("models/gst.pt")
    return [model] if ctx.params.include_trained and model.is_file() else []


STAGE = Stage(
    name="bench",
    run=run,
    params_model=BenchSettings,
    applies=lambda scene: scene.is_synthetic,
    outputs=lambda ctx: ["reports/bench"],
    inputs=_trained_model,
    in_all=False,  # a sweep over model variants: `python -m pipeline run bench` when wanted
    help="run time against error for model variants (needs a scene with truth)",
)
