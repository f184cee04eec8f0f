"""Settings, errors and the report of a scene extraction (`gst.data.extract.extract_scene`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from calibration.camera import FRAME_PADDING_TOLERANCE
from gst.data.association import (
    AssociationConfig,
    CaptureVolume,
)
from gst.data.background import BackgroundConfig
from gst.data.keypoints.people import CrowdConfig
from gst.data.masks import MaskConfig
from gst.detect.persons import SegmenterConfig
from gst.records import Record

WORK_MAX_SIDE = 960  # default work resolution: longer image side in pixels
ASSOCIATION_METHODS = ("auto", "keypoints", "hull")


class ExtractError(ValueError):
    """The extraction cannot proceed; the message names the camera, file or setting."""


def association_overrides(value: dict | None) -> dict | None:
    """`value` if each key is a field of `AssociationConfig`, else a ValueError naming the
    unknown keys and the known ones (for the stage's params: a typo was found only when
    extraction began, after the stages before it had run)."""
    import dataclasses

    known = {f.name for f in dataclasses.fields(AssociationConfig)}
    unknown = sorted(set(value or {}) - known)
    if unknown:
        raise ValueError(
            f"association: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})"
        )
    AssociationConfig(**(value or {}))  # its own range checks, before any stage runs
    return value


@dataclass(frozen=True, eq=False)
class ExtractOptions:
    """Advanced settings of `extract_scene` (the common ones are its keyword arguments)."""

    work_scale: float | None = (
        None  # mask resolution / video resolution; None: longer side <= 960 px
    )
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    volume: CaptureVolume | None = None  # None: derived from where the cameras look
    compression: str = "gzip"
    compression_level: int = 1
    commit_frames: int = 16  # frames per store commit (the unit of resume)
    keep_work: bool = False  # keep `<store>.work/` after success (for debugging)
    # camera -> video of the empty scene (a "clean plate"): the background is learnt from it
    # instead of the capture itself, which is what makes people who barely move visible.
    background_videos: dict[str, Path] | None = None
    # Learned person masks (BlazePose, gst.detect) instead of background subtraction: finds
    # people who stand still. None: background model only.
    persons: SegmenterConfig | None = None
    persons_models_dir: str | None = None  # None: the default cache (python -m gst.detect fetch)
    # Also segment around moving background blobs (finds movers the detector misses).
    persons_hints: bool = True
    # The person detector every this many frames while everyone is tracked (SegmenterConfig)
    person_detect_every: int = 10
    # the person detector looks again zoomed in (SegmenterConfig.zoom; docs/extract.md "The
    # bystander, zoomed in"); 0: not
    person_zoom: float = 2 / 3
    # Frames smaller than the calibrated size by up to this many pixels are encoder padding
    # (calibration.camera.fit_to_frames).
    frame_size_tolerance: int = FRAME_PADDING_TOLERANCE
    # Who is who across cameras: 'keypoints' (BlazePose instances on every camera, matched by
    # their landmarks' geometry and tracked in 3D: gst.data.keypoints), 'hull' (the visual
    # hull of the foreground), or 'auto' (keypoints when the detect extra and the BlazePose
    # models are installed, else the hull; external masks always use the hull).
    association_method: str = "auto"
    crowd: CrowdConfig = field(default_factory=CrowdConfig)  # the keypoint association
    # the videos' frame rate where their headers are not to be trusted (the scene's `fps`; a raw
    # stream reads at FFmpeg's 25): the keypoint tracker's time step; None: the first video's
    fps: float | None = None

    def __post_init__(self):
        if self.association_method not in ASSOCIATION_METHODS:
            raise ExtractError(
                f"association_method must be one of {ASSOCIATION_METHODS}, "
                f"got {self.association_method!r}"
            )
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ExtractError(f"fps must be > 0 frames/s, got {self.fps!r}")
        if int(self.commit_frames) < 1:
            # 0 crashed in the merge after every camera's crops; a negative value merged no
            # crop and marked the store complete
            raise ExtractError(f"commit_frames must be at least 1, got {self.commit_frames!r}")

    @classmethod
    def from_settings(
        cls,
        background_videos: dict[str, Path] | None = None,
        association: dict[str, float | int] | None = None,
        person_model: str = "none",
        person_hints: bool = True,
        frame_size_tolerance: int = FRAME_PADDING_TOLERANCE,
        association_method: str = "auto",
        person_detect_every: int = 10,
        reuse_detections: bool = False,
        person_zoom: float = 2 / 3,
        single_view_search: bool = True,
        fps: float | None = None,
    ) -> ExtractOptions:
        """Options from a stage's flat settings: clean plates, association overrides, the person
        model ('none' or 'blazepose'), whether to segment around moving blobs too, the
        association method ('auto', 'keypoints' or 'hull'), how often the person detector
        runs while everyone is tracked, and whether the keypoint association keeps the
        detections of people no one overlaps instead of looking at them again
        (`CrowdConfig.reuse_detections`), how much the detector zooms in when it looks
        again (`SegmenterConfig.zoom`), and whether a single-view person is looked for where
        they would stand in the other cameras (`CrowdConfig.single_view_search`), and the
        videos' frame rate where their headers are not trusted."""
        if person_model not in ("none", "blazepose"):
            raise ExtractError(f"person_model must be 'none' or 'blazepose', got {person_model!r}")
        return cls(
            background_videos=background_videos,
            association=AssociationConfig(**(association or {})),
            persons=(
                SegmenterConfig(detect_every=person_detect_every, zoom=person_zoom)
                if person_model == "blazepose"
                else None
            ),
            persons_hints=person_hints,
            person_detect_every=person_detect_every,
            person_zoom=person_zoom,
            frame_size_tolerance=frame_size_tolerance,
            association_method=association_method,
            crowd=CrowdConfig(
                reuse_detections=reuse_detections, single_view_search=single_view_search
            ),
            fps=fps,
        )


@dataclass
class CameraReport:
    """Per-camera outcome."""

    crops: int = 0
    frames_with_people: int = 0
    frames_without_people: int = 0
    seconds_masks: float = 0.0
    seconds_crops: float = 0.0
    mask_iou: float | None = None  # mean over this run's crops, when truth was given


@dataclass
class SourceScore:
    """Synthetic truth, per source of the views (the keypoint association's 'refined',
    'detected', 'projected' and 'single'; '' for the visual hull): how good that kind of view is,
    and what it costs the rest (docs/extract.md, "Where the crowd IoU and association are lost")."""

    crops: int
    mask_iou: float  # mean over these crops
    # association accuracy of all the other scored crops (these left out); None when none remain
    association_without: float | None


@dataclass
class ExtractReport(Record):
    """What `extract_scene` did. Counts cover the whole store; truth scores this run's crops."""

    store: str
    cameras: list[str]
    frames_total: int
    frame_stride: int
    frames_considered: int
    frames_with_people: int
    frames_skipped_empty: int
    cameras_skipped: list[str]  # saw no one in any frame
    per_camera: dict[str, CameraReport]
    crops: int
    persons: int  # distinct person ids
    multiview_groups: int  # (frame, person) with crops from >= 2 cameras
    pairs_resumed: int  # (frame, camera) pairs found already done
    short_tracks_dropped: list[int] = field(default_factory=list)  # ids seen too briefly to crop
    mask_iou: float | None = None
    association_accuracy: float | None = None
    crops_scored: int = 0
    truth_views: int = 0  # (frame, camera, person) truth views big enough to count
    truth_views_missed: int = 0
    # Synthetic scenes: truth views where >= 30% of the person's joints are visible, and those
    # no crop covers (a stricter count than `truth_views`, which goes by mask area).
    visible_views: int = 0
    visible_views_missed: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    association_method: str = "hull"  # the path that ran: 'keypoints' or 'hull'
    single_view_crops: int = 0  # crops of people only one camera saw (keypoint path)
    truth_by_source: dict[str, SourceScore] = field(default_factory=dict)
    # synthetic scenes: per extracted id, its frames and its crops per truth person
    # (gst.data.extract.scene.ids_against_truth)
    truth_by_id: dict[str, dict] = field(default_factory=dict)

    def summary_line(self) -> str:
        return (
            f"{self.crops} crops of {self.persons} people, {self.multiview_groups} multi-view "
            f"groups ({self.association_method} association); "
            + (
                "no truth to score against"
                if self.mask_iou is None and self.association_accuracy is None
                else f"mask IoU {_shown(self.mask_iou)}; association "
                f"{_shown(self.association_accuracy)}"
            )
        )


def _shown(value: float | None) -> str:
    """A truth score for the log: 3 decimals, or n/a where nothing was scored."""
    return "n/a" if value is None else f"{value:.3f}"
