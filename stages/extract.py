"""extract: person crops, masks and crop intrinsics from every camera into `crops/crops.h5`.

Library: `gst.data.extract_scene` (docs/extract.md, docs/formats/crops_h5.md). Supplied
masks/boxes (`scenes.NAME.masks`) take precedence over the background model; `person_model:
blazepose` segments people with a learned model instead (docs/person_models.md). Synthetic
scenes learn their background from the board clip, which shows the empty stage; real scenes can
name empty-room clips in `background_videos`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, PositiveInt

from gst.data import ExtractOptions, extract_scene, write_extract_report
from gst.data.extract.options import association_overrides
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    crop_size: int = Field(256, ge=16)  # side of the square crops (px)
    scale: float = Field(1.2, ge=1.0)  # HMR2: square side = 1.2 x the person box's longer side
    frame_stride: PositiveInt = 1  # every Nth frame
    method: Literal["median", "mog2", "knn"] = "median"  # the background model
    background_videos: dict[str, Path] | None = None  # camera -> clip of the empty scene
    use_board_clip_as_background: bool = True  # synthetic scenes: the board clip is an empty stage
    # Overrides of gst.data.AssociationConfig, e.g. {merge_radius: 0.6, peak_separation: 0.8}.
    association: Annotated[dict[str, float | int] | None, AfterValidator(association_overrides)] = (
        None
    )
    # 'blazepose': learned person masks (the `detect` extra; docs/person_models.md).
    person_model: Literal["none", "blazepose"] = "none"
    person_hints: bool = True  # also segment around moving background blobs
    person_detect_every: int = Field(10, ge=1)  # BlazePose detector every N frames (tracked)
    person_zoom: float = Field(2 / 3, ge=0, lt=1)  # look again zoomed in (SegmenterConfig.zoom)
    # 'auto': keypoint association when BlazePose is installed, else the visual hull
    association_method: Literal["auto", "keypoints", "hull"] = "auto"
    # keypoints: keep the detections of people no one overlaps instead of looking at them again
    # (about 9 % faster; in crowds results move both ways: docs/extract.md "Speed")
    reuse_detections: bool = False
    # keypoints: look for a single-view person where they would stand in the other cameras
    single_view_search: bool = True


def run(ctx: StageContext) -> None:
    p, videos = ctx.params, ctx.camera_videos()
    plates = ctx.background_plates(p.background_videos, p.use_board_clip_as_background)
    options = ExtractOptions.from_settings(
        plates, p.association, p.person_model, p.person_hints, ctx.scene.frame_size_tolerance,
        p.association_method, p.person_detect_every, p.reuse_detections, p.person_zoom,
        p.single_view_search, ctx.scene.fps,
    )  # fmt: skip
    report = extract_scene(
        videos, ctx.rig(), ctx.out("crops/crops.h5"), crop_size=p.crop_size, scale=p.scale,
        frame_stride=p.frame_stride, method=p.method, external=ctx.scene.masks,
        truth=ctx.path("synth/truth") if ctx.scene.is_synthetic else None, progress=ctx.progress,
        executor_map=ctx.executor.map if ctx.executor is not None else None, options=options,
    )  # fmt: skip
    # the report names the store where it will be, not the staging folder the run wrote it in
    report = dataclasses.replace(report, store=str(ctx.path("crops/crops.h5")))
    write_extract_report(report, ctx.out("crops/crops.h5"), ctx.out("reports/extract"))
    ctx.log.info("extract: %s", report.summary_line())


STAGE = Stage(
    inputs=lambda ctx: ctx.input_videos(ctx.params.background_videos) + (
        [ctx.scene.masks] if ctx.scene.masks is not None else []
    ),
    name="extract", run=run, params_model=Params,
    outputs=lambda ctx: ["crops", "reports/extract"],
    help="person crops and masks from every camera (the learned person model, or the background "
    "model; multi-view association)",
)  # fmt: skip
