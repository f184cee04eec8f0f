"""bodycrops: person crops cut again from the fitted bodies into `bodycrops/crops.h5`.

Library: `gst.fuse.body_crops.recut_crops` (docs/fuse.md "Crops from the fitted bodies"). The
fused bodies, projected into every camera, share the foreground among the people by whose
surface is in front: fused ids in every camera, a crop in every view that shows the person, and
in crowds masks nearer the truth than the extraction's. The store has the extraction's format
(docs/formats/crops_h5.md); training reads it with `train.crops: bodycrops`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from gst.data.background import BackgroundConfig
from gst.fuse.body_crops import BodyCropOptions, recut_crops, write_body_crop_report
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    # foreground this far (pixels at the extraction's working size) from every body is nobody's
    max_distance_px: float = Field(8.0, ge=0)
    min_pixels: int = Field(20, ge=1)  # smaller visible areas get no crop
    # the background as the extraction learnt it (set these as you set extract's)
    method: Literal["median", "mog2", "knn"] = "median"
    background_videos: dict[str, Path] | None = None  # camera -> clip of the empty scene
    use_board_clip_as_background: bool = True  # synthetic scenes: the board clip is an empty stage


def run(ctx: StageContext) -> None:
    p = ctx.params
    store = ctx.out("bodycrops/crops.h5")
    report = recut_crops(
        ctx.path("crops/crops.h5"), ctx.rig(), ctx.camera_videos(),
        ctx.path("fused/bodies.parquet"), store,
        plates=ctx.background_plates(p.background_videos, p.use_board_clip_as_background),
        options=BodyCropOptions(
            max_distance_px=p.max_distance_px, min_pixels=p.min_pixels,
            background=BackgroundConfig(method=p.method),
        ),
        truth_dir=ctx.path("synth") if ctx.scene.is_synthetic else None, progress=ctx.progress,
    )  # fmt: skip
    write_body_crop_report(report, store, ctx.out("reports/bodycrops"))
    ctx.log.info("bodycrops: %s", report.summary_line())


def _inputs(ctx: StageContext) -> list[Path]:
    files = [] if ctx.scene.is_synthetic else list(ctx.scene.video_files())
    return files + list((ctx.params.background_videos or {}).values())


STAGE = Stage(
    name="bodycrops", run=run, params_model=Params, inputs=_inputs,
    outputs=lambda ctx: ["bodycrops", "reports/bodycrops"],
    help="person crops and masks cut again from the fitted bodies (fused ids, every view)",
)  # fmt: skip
