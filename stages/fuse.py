"""fuse: one world-space body per person and frame from all cameras (docs/fuse.md).

Library: `gst.fuse.fuse_scene` (landmarks per crop, crowded crops read again, people regrouped,
robust triangulation, a body fit over the clip). Writes `fused/` (Parquet, TRC, C3D;
docs/formats/fused_*.md) and `reports/fuse/` (report, overlays; synthetic scenes: the error).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from gst.fuse import FitOptions, FuseOptions, RegroupOptions, TriangulationOptions, fuse_scene
from pipeline.stage import Stage, StageContext, StageParams


class Params(StageParams):
    body_model: str = "anny"  # or "smpl", or a path to your SMPL file (docs/body_model.md)
    markers: str | None = None  # a markers JSON (gst.fuse.fit_markers); None: the package's
    iterations: int = 12  # Levenberg-Marquardt iterations of the body fit, per round (docs/fuse.md)
    smoothness: float = 1.0  # weight of the temporal smoothness term
    fill_gaps_s: float = Field(0.1, ge=0)  # unseen frames filled in gaps up to this long
    regroup: bool = True  # people regrouped by 3D agreement and tracked (docs/fuse.md)
    refine_rig: int = 0  # rounds of camera rotations corrected from the fitted bodies
    # > 0: RANSAC over view pairs per landmark, among this many views (0: leave-one-out only)
    pair_consensus: int = Field(8, ge=0)
    # where people are in each view (docs/fuse.md): a view covering a pair hypothesis counts
    # this much beside a view whose landmark agrees (0: landmarks only)
    silhouette_votes: float = Field(1.0, ge=0)
    silhouette_fit: float = Field(0.0, ge=0)  # > 0: the fit pulls markers onto the people
    temporal_votes: float = Field(2.0, ge=0)  # a hypothesis near its neighbours in time
    # rounds of view limb groups exchanged where the fitted body says they were read mirrored
    exchange_rounds: int = Field(1, ge=0)
    relook: bool = True  # crowded crops read again with the other people painted over
    # the floor (height along the rig's up axis, m) that feet do not sink into; auto: 0 where the
    # feet stand near it; null: none (docs/fuse.md "Floor")
    floor: float | Literal["auto"] | None = "auto"
    people_per_batch: int = 8
    overlay: bool = True  # one video per camera with the fitted bodies drawn in


def run(ctx: StageContext) -> None:
    p = ctx.params
    result = fuse_scene(
        ctx.path("crops/crops.h5"), ctx.rig(), ctx.out("fused"), ctx.out("reports/fuse"),
        fps=ctx.scene.fps, videos=ctx.camera_videos(),
        options=FuseOptions(
            body_model=p.body_model, markers=p.markers,
            fit=FitOptions(
                iterations=p.iterations, w_smooth=p.smoothness, w_silhouette=p.silhouette_fit,
                max_gap_s=p.fill_gaps_s,
            ),
            triangulation=TriangulationOptions(
                consensus_views=p.pair_consensus,
                silhouette_weight=p.silhouette_votes,
                temporal_weight=p.temporal_votes,
            ),
            silhouettes=p.silhouette_votes > 0 or p.silhouette_fit > 0,
            regroup=RegroupOptions() if p.regroup else None,
            refine_rig_rounds=p.refine_rig, exchange_rounds=p.exchange_rounds,
            relook=FuseOptions().relook if p.relook else None,
            floor=p.floor, people_per_batch=p.people_per_batch, overlay=p.overlay,
        ),
        truth_dir=ctx.path("synth") if ctx.scene.is_synthetic else None,
        progress=ctx.progress, log=ctx.log,
    )  # fmt: skip
    ctx.log.info("%s", result.summary.headline())


STAGE = Stage(
    name="fuse",
    run=run,
    params_model=Params,
    outputs=lambda ctx: ["fused", "reports/fuse"],
    resumable=True,
    help="world-space bodies from all cameras: triangulation + body fit (Parquet, TRC, C3D)",
)
