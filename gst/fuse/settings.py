"""The fuse stage's parameters (`stages.fuse`, pipeline.yaml `stages.fuse.params`), validated,
and the library options they stand for (docs/fuse.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, NonNegativeInt, PositiveInt

from calibration.camera import FRAME_PADDING_TOLERANCE
from gst.data.background import BackgroundConfig
from gst.fuse.body_crops import BodyCropOptions
from gst.fuse.fit import FitOptions
from gst.fuse.regroup import RegroupOptions
from gst.fuse.scene import FuseOptions
from gst.fuse.triangulate import TriangulationOptions
from gst.param_types import NAMES_FILE

__all__ = ["FuseSettings"]


class FuseSettings(BaseModel):
    # NaN or infinity is refused before any stage runs (a NaN smoothness gave NaN bodies)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    # "anny", "smpl", or a path to your SMPL file (docs/body_model.md)
    body_model: str = Field("anny", json_schema_extra=NAMES_FILE)
    # a markers JSON (gst.fuse.fit_markers); None: the package's
    markers: str | None = Field(None, json_schema_extra=NAMES_FILE)
    iterations: PositiveInt = (
        12  # Levenberg-Marquardt iterations of the body fit, per round (docs/fuse.md)
    )
    smoothness: float = Field(1.0, ge=0)  # weight of the temporal smoothness term
    fill_gaps_s: float = Field(0.1, ge=0)  # unseen frames filled in gaps up to this long
    regroup: bool = True  # people regrouped by 3D agreement and tracked (docs/fuse.md)
    refine_rig: NonNegativeInt = 0  # rounds of camera rotations corrected from the fitted bodies
    # > 0: RANSAC over view pairs per landmark, among this many views (0: leave-one-out only)
    pair_consensus: int = Field(8, ge=0)
    # where people are in each view (docs/fuse.md): a view covering a pair hypothesis counts
    # this much beside a view whose landmark agrees (0: landmarks only)
    silhouette_votes: float = Field(1.0, ge=0)
    silhouette_fit: float = Field(0.0, ge=0)  # > 0: the fit pulls markers onto the people
    temporal_votes: float = Field(2.0, ge=0)  # a hypothesis near its neighbours in time
    # a view's landmark this far from the point (full-image px; crop px on crops larger than
    # their stored size) disagrees with it / is an outlier (docs/fuse.md)
    outlier_px: float = Field(12.0, gt=0)
    # rounds of view limb groups exchanged where the fitted body says they were read mirrored
    exchange_rounds: int = Field(1, ge=0)
    relook: bool = True  # crowded crops read again with the other people painted over
    # the floor (height along the rig's up axis, m) that feet do not sink into; auto: 0 where the
    # feet stand near it; null: none (docs/fuse.md "Floor")
    floor: float | Literal["auto"] | None = "auto"
    people_per_batch: PositiveInt = 8  # people fitted together in one batch of the body fit
    overlay: bool = True  # one video per camera with the fitted bodies drawn in
    # Crops cut again from the fitted bodies (`bodycrops/crops.h5`, docs/fuse.md "Crops from the
    # fitted bodies"), and rounds of fusing again on such crops before the last cut (0: fuse
    # the extraction's crops only; the last cut is made either way).
    recut_rounds: int = Field(1, ge=0)
    # a cut that agrees with the extraction at least this much (the share of crops of either
    # that pair one to one with one of the other's by mask overlap) ends the rounds: the
    # extraction had already found each person's views (the demo 0.991, the lab capture 1.000;
    # the six crowd scenes 0.80-0.955, where fusing again helped); null: every round runs
    recut_agreement: float | None = Field(0.98, ge=0)
    # foreground this far (pixels at the extraction's working size) from every body is nobody's
    max_distance_px: float = Field(8.0, ge=0)
    min_pixels: int = Field(20, ge=1)  # smaller visible areas get no crop
    # the background as the extraction learnt it (set these as you set extract's)
    method: Literal["median", "mog2", "knn"] = "median"
    background_videos: dict[str, Path] | None = None  # camera -> clip of the empty scene
    use_board_clip_as_background: bool = True  # synthetic scenes: the board clip is an empty stage

    def fuse_options(self) -> FuseOptions:
        return FuseOptions(
            body_model=self.body_model, markers=self.markers,
            fit=FitOptions(
                iterations=self.iterations, w_smooth=self.smoothness,
                w_silhouette=self.silhouette_fit, max_gap_s=self.fill_gaps_s,
            ),
            triangulation=TriangulationOptions(
                consensus_views=self.pair_consensus, silhouette_weight=self.silhouette_votes,
                temporal_weight=self.temporal_votes, outlier_px=self.outlier_px,
            ),
            silhouettes=self.silhouette_votes > 0 or self.silhouette_fit > 0,
            regroup=RegroupOptions() if self.regroup else None,
            refine_rig_rounds=self.refine_rig, exchange_rounds=self.exchange_rounds,
            relook=FuseOptions().relook if self.relook else None,
            floor=self.floor, people_per_batch=self.people_per_batch, overlay=self.overlay,
        )  # fmt: skip

    def crop_options(self, frame_size_tolerance: int = FRAME_PADDING_TOLERANCE) -> BodyCropOptions:
        """The cut's options; `frame_size_tolerance`: the scene's (encoder padding)."""
        return BodyCropOptions(
            max_distance_px=self.max_distance_px, min_pixels=self.min_pixels,
            background=BackgroundConfig(method=self.method),
            frame_size_tolerance=frame_size_tolerance,
        )  # fmt: skip
