"""extract: person crops, masks and crop intrinsics from every camera into `crops/crops.h5`.

Library: `gst.data.extract_scene` (docs/extract.md, docs/formats/crops_h5.md). Supplied
masks/boxes (`scenes.NAME.masks`) take precedence over the background model; `person_model:
blazepose` segments people with a learned model instead (real footage, people who stand
still; docs/person_models.md). Synthetic scenes learn their background from the board clip,
which shows the empty stage (the board moves, so the temporal median removes it); real scenes
can name empty-room clips in `background_videos`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from calibration.formats import read_rig
from gst.data import AssociationConfig, ExtractOptions, extract_scene, write_extract_report
from gst.detect.persons import SegmenterConfig
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    crop_size: int = 256
    scale: float = 1.2  # HMR2 convention: square side = 1.2 x the person box's longer side
    frame_stride: int = 1
    method: Literal["median", "mog2", "knn"] = "median"
    background_videos: dict[str, Path] | None = None  # camera -> clip of the empty scene
    use_board_clip_as_background: bool = True  # synthetic scenes: the board clip is an empty stage
    # Overrides of gst.data.AssociationConfig, e.g. {merge_radius: 0.6, peak_separation: 0.8}
    # for background-model masks of people who stay >= 0.8 m apart and lunge.
    association: dict[str, float | int] | None = None
    # 'blazepose': learned person masks (finds people who stand still; needs the `detect` extra
    # and `python -m gst.detect fetch`, docs/person_models.md). 'none': background model only.
    person_model: Literal["none", "blazepose"] = "none"
    person_hints: bool = True  # also segment around moving background blobs


def _videos(ctx: StageContext) -> dict[str, Path]:
    if ctx.scene.is_synthetic:
        return {p.stem: p for p in sorted(ctx.path("synth/videos").glob("*.mp4"))}
    return {p.stem: p for p in ctx.scene.video_files()}


def run(ctx: StageContext) -> None:
    p = ctx.params
    rig = read_rig(ctx.path("calibration/rig.json"), "rig")
    videos = _videos(ctx)
    if not videos:
        raise FileNotFoundError(f"scene '{ctx.scene_name}' has no camera videos")
    plates = p.background_videos
    if plates is None and ctx.scene.is_synthetic and p.use_board_clip_as_background:
        plates = {n: ctx.path(f"synth/board/{n}.mp4") for n in videos}
    truth = ctx.path("synth/truth") if ctx.scene.is_synthetic else None
    executor_map = ctx.executor.map if ctx.executor is not None else None
    store = ctx.out("crops/crops.h5")
    report = extract_scene(
        videos,
        rig,
        store,
        crop_size=p.crop_size,
        scale=p.scale,
        frame_stride=p.frame_stride,
        method=p.method,
        external=ctx.scene.masks,
        truth=truth,
        progress=ctx.progress,
        executor_map=executor_map,
        options=ExtractOptions(
            background_videos=plates,
            association=AssociationConfig(**(p.association or {})),
            persons=SegmenterConfig() if p.person_model == "blazepose" else None,
            persons_hints=p.person_hints,
        ),
    )
    write_extract_report(report, store, ctx.out("reports/extract"))
    ctx.log.info(
        "extract: %d crops of %d people, %d multi-view groups; mask IoU %s; association %s",
        report.crops,
        report.persons,
        report.multiview_groups,
        report.mask_iou,
        report.association_accuracy,
    )


def _inputs(ctx: StageContext) -> list[Path]:
    files = [] if ctx.scene.is_synthetic else list(ctx.scene.video_files())
    if ctx.params.background_videos:
        files += list(ctx.params.background_videos.values())
    return files


STAGE = Stage(
    name="extract",
    run=run,
    params_model=Params,
    inputs=_inputs,
    outputs=lambda ctx: ["crops", "reports/extract"],
    help="person crops and masks from every camera (background model, multi-view association)",
)
