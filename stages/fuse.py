"""fuse: one world-space body per person and frame from all cameras (docs/fuse.md).

Library: `gst.fuse.rounds.fuse_rounds` over `gst.fuse.fuse_scene` (landmarks per crop, crowded
crops read again, people regrouped, robust triangulation, a body fit over the clip), then the
crops cut again from the fitted bodies and fused again (`fuse.recut_rounds`, unless the cut
agrees with the extraction: `fuse.recut_agreement`), and cut from the final bodies. Writes
`fused/` (Parquet, TRC, C3D; docs/formats/fused_*.md), `reports/fuse/` (report, overlays;
synthetic scenes: the error), `bodycrops/crops.h5` (the crops cut from the final bodies,
docs/formats/crops_h5.md) and `reports/bodycrops/`.
"""

from __future__ import annotations

from gst.fuse.rounds import fuse_rounds
from gst.fuse.settings import FuseSettings
from pipeline.stage import READINGS, Stage, StageContext


def run(ctx: StageContext) -> None:
    p: FuseSettings = ctx.params
    result = fuse_rounds(
        ctx.path("crops/crops.h5"), ctx.rig(), ctx.out("fused"), ctx.out("reports/fuse"),
        ctx.out("bodycrops/crops.h5"), ctx.out("reports/bodycrops"), rounds=p.recut_rounds,
        skip_agreement=p.recut_agreement, fps=ctx.scene.fps, options=p.fuse_options(),
        crop_options=p.crop_options(ctx.scene.frame_size_tolerance), videos=ctx.camera_videos(),
        plates=ctx.background_plates(p.background_videos, p.use_board_clip_as_background),
        truth_dir=ctx.path("synth") if ctx.scene.is_synthetic else None,
        progress=ctx.progress, log=ctx.log, reading_cache=ctx.path(READINGS),
    )  # fmt: skip
    fusions = f"{result.fusions} fusion" + ("s" if result.fusions != 1 else "")
    ctx.log.info("fuse: %s (%s)", result.fused.summary.headline(), fusions)
    ctx.log.info("bodycrops: %s", result.crops.summary_line())


STAGE = Stage(
    inputs=lambda ctx: ctx.input_videos(ctx.params.background_videos),
    name="fuse", run=run, params_model=FuseSettings, resumable=True,
    outputs=lambda ctx: ["fused", "reports/fuse", "bodycrops", "reports/bodycrops"],
    help="world-space bodies from all cameras: triangulation + body fit (Parquet, TRC, C3D), "
    "and the crops cut again from them",
)  # fmt: skip
