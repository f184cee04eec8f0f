"""synth: render the scene's synthetic capture (videos, board clip, calibration files, truth).

Only synthetic scenes need it. Output layout: docs/formats/synth_scene.md, under `synth/`.
"""

from __future__ import annotations

from pathlib import Path

from gst.body import body_model_file
from pipeline.stage import Stage, StageContext, StageParams
from synth.scene import preset, render_scene


class Params(StageParams):
    pass  # everything that defines the capture lives in the scene's `synthetic` block


def run(ctx: StageContext) -> None:
    src = ctx.scene.synthetic  # validated with the config (pipeline.config.SyntheticSource)
    spec = preset(src.preset, seed=src.seed, **src.overrides)
    last = {}

    def progress(step: str, done: int, total: int) -> None:
        if done == total or step not in last:
            last[step] = done
            ctx.log.info("%s: %d/%d", step, done, total)

    # Camera shares fan out through the executor (--executor local|ray), one share per worker;
    # the files are identical to a serial render either way. One worker renders inline
    # (per-frame progress).
    workers = getattr(ctx.executor, "workers", 1)
    fan_out = ctx.executor is not None and workers > 1
    summary = render_scene(
        spec,
        ctx.out("synth"),
        progress=progress,
        map_fn=ctx.executor.map if fan_out else None,
        shares=workers if fan_out else None,
    )
    ctx.log.info(
        "rendered %d frames x %d cameras (%d people) in %.1f s; %.1f%% of GT joints inside their "
        "mask",
        summary.n_frames,
        len(summary.cameras),
        summary.n_people,
        summary.seconds,
        100 * summary.joints_in_mask,
    )


def _body_file(ctx: StageContext) -> list[Path]:
    """The file the scene's `body_model` reads (`smpl`, or a file of the user's): an input, so
    a swapped SMPL file renders the scene again (it was left 'up to date')."""
    src = ctx.scene.synthetic
    file = body_model_file(preset(src.preset, seed=src.seed, **src.overrides).body_model)
    return [file] if file is not None else []


STAGE = Stage(
    name="synth",
    run=run,
    params_model=Params,
    inputs=_body_file,
    outputs=lambda ctx: ["synth"],
    applies=lambda scene: scene.is_synthetic,
    help="render the synthetic capture with exact truth (synthetic scenes only)",
)
