"""Track one video end to end: decode, detect, crop, predict in batches, track, smooth, write.

Work proceeds in groups of `frames_per_group` processed frames. Within a group, crops from
consecutive frames are pooled and predicted `batch_size` at a time; then the group's frames are
tracked in order and its rows are committed as one row group, together with the tracker and
smoother state. A rerun resumes after the last committed group and, because batches never span
groups, reproduces an uninterrupted run byte for byte.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from calibration import Camera
from gst.body.markers import BLAZEPOSE_MIRROR
from gst.data.camera_view import TrackingView, focal_from_35mm
from gst.device import module_on
from gst.model.landmarks import camera_up
from gst.prefetch import background
from gst.track.align import AlignmentConfig, align_translation
from gst.track.appearance import DESCRIPTOR_SIZE
from gst.track.detection import N_LANDMARKS, Detection, Detector
from gst.track.detection_cache import RecordingDetector, detections_key, load_detections
from gst.track.frames import (
    PendingFrame,
    PreparedDetection,
    TrackingSession,
    is_blank,
    prepare_detection,
)
from gst.track.mirror import LabelSmoother, MirrorConfig
from gst.track.pose_fit import PoseFitConfig, PoseFitter
from gst.track.predictor import PoseBatch, Predictor, validate_prediction
from gst.track.rows import RowSet, rows_table
from gst.track.schema import FORMAT_VERSION, file_metadata, tracks_schema
from gst.track.smoothing import OneEuroConfig
from gst.track.tracker import TrackerConfig
from gst.track.writer import TrackWriter
from gst.video import (
    Frame,
    VideoError,
    VideoInfo,
    VideoTruncatedError,
    content_digest,
    frame_range,
    iter_frames,
    probe_video,
)

log = logging.getLogger("gst.track")


@dataclass(frozen=True)
class TrackOptions:
    stride: int = 1  # process every stride-th frame
    start_s: float | None = None  # time range [start_s, end_s) in seconds
    end_s: float | None = None
    crop_size: int = 256
    batch_size: int = 32  # crops per predictor call, pooled across frames
    frames_per_group: int = 100  # processed frames per committed row group (work lost on a kill)
    min_score: float = 0.0  # detections scoring below this are ignored
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    smoothing: OneEuroConfig | None = None  # None: raw per-frame values
    prefetch: int = (
        4  # frames decoded, detected and cropped ahead in a thread (0: inline); same output
    )
    row_group_rows: int = 65536  # row-group size of the finished file
    # move each body onto its crop's confident landmarks (gst.track.align); None: the network's
    align: AlignmentConfig | None = field(default_factory=AlignmentConfig)
    # then bend each body's pose onto its landmarks where it disagrees with them
    # (gst.track.pose_fit; needs a predictor with a `body` model); None: the network's pose
    pose_fit: PoseFitConfig | None = None
    # a video that is no calibrated camera: its lens's 35 mm equivalent focal length (mm), where
    # known; None: the image diagonal (gst.data.camera_view)
    focal_35mm: float | None = None
    # each person's landmark labels kept continuous in time, BlazePose's whole-body left/right
    # flips undone (gst.track.mirror; output delayed by its lag); None: the labels as detected
    unmirror: MirrorConfig | None = field(default_factory=MirrorConfig)
    # the video's frame rate where its header is not to be trusted (a raw .h264/.mjpeg stream
    # is read at FFmpeg's 25; the scene's `fps`): frame times, the time range and every rate
    # follow it; None: the container's rate
    fps: float | None = None

    def __post_init__(self):
        for name in ("stride", "crop_size", "batch_size", "frames_per_group", "row_group_rows"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrackOptions.{name} must be >= 1, got {getattr(self, name)}")
        if self.focal_35mm is not None and not self.focal_35mm > 0:
            raise ValueError(f"TrackOptions.focal_35mm must be > 0 mm, got {self.focal_35mm}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"TrackOptions.fps must be > 0 frames/s, got {self.fps}")

    def settings(self) -> dict:
        """What determines the output (prefetch does not)."""
        d = asdict(self)
        d.pop("prefetch")
        if d["fps"] is None:  # not given: the keys of the files tracked before it existed hold
            d.pop("fps")
        return d


CROP_DESCRIPTION = (
    "HMR2: square side 1.2 x max(w, h) of the box, centred, resized, zero padding outside the frame"
)


@dataclass(frozen=True)
class TrackResult:
    path: Path
    rows: int
    frames: int  # processed frames, this run and earlier runs it resumed
    persons: int
    resumed_from_frame: int | None
    seconds: float
    # the person detector's work: "run", "run and kept" (for the next run over the video),
    # "replayed" (kept by an earlier run; gst.track.detection_cache) or DETECTIONS_NOT_NEEDED
    detections: str = "run"

    @property
    def kept_finished(self) -> bool:
        """The video's file was found finished with these settings and kept: this run tracked
        nothing (its `seconds` are only the time it took to notice)."""
        return self.detections == DETECTIONS_NOT_NEEDED


DETECTIONS_NOT_NEEDED = "not needed (the finished file was kept)"


def _axes_json(calibrated: bool, world_up) -> dict:
    axes = {
        "camera": "OpenCV: x right, y down, z forward (metres)",
        "joints3d": "world" if calibrated else "camera",
        "body": (
            "the body model's (gst.model.body_model) SMPL joint layout: global_orient rotates the "
            "body frame (x left, y up, z forward) into joints3d's frame"
        ),
    }
    if calibrated:
        axes["world"] = {
            "description": "the rig's world frame (metres), X_cam = R X_world + t",
            "up": None if world_up is None else [float(v) for v in world_up],
        }
    else:
        axes["world"] = None
        axes["world_note"] = (
            "unavailable: the video is not a calibrated camera (default pinhole camera, "
            "gst.calibration); joints3d and transl_cam are in the camera frame"
        )
    return axes


def needs_pixels(predictor: Predictor, landmarks: np.ndarray) -> np.ndarray:
    """(N,) bool: which detections' crops the predictor reads (every one, unless it declares
    `needs_pixels(landmarks)`, as `GSTPredictor` does for pose from the landmarks)."""
    ask = getattr(predictor, "needs_pixels", None)
    return np.ones(len(landmarks), bool) if ask is None else np.asarray(ask(landmarks), bool)


def accepts_landmarks(predictor: Predictor) -> bool:
    """Whether the predictor takes the crops' 2D landmarks (`landmarks=` keyword, (B, 33, 3)
    u, v in crop pixels + confidence, NaN rows where the detector gave none)."""
    return bool(getattr(predictor, "accepts_landmarks", False))


def accepts_up(predictor: Predictor) -> bool:
    """Whether the predictor reads the world's up direction in the camera (`up=` keyword,
    (B, 3); a gravity-aware GST checkpoint, `GSTConfig.landmark_gravity`)."""
    return bool(getattr(predictor, "accepts_up", False))


def camera_frame_up(run: VideoRun) -> np.ndarray | None:
    """The world's up axis in the run's camera frame, or None for an uncalibrated video (or a
    calibrated camera without a world up)."""
    world_up = run.settings.get("world_up")
    if not run.view.calibrated or world_up is None:
        return None
    R = torch.as_tensor(run.view.camera.R, dtype=torch.float64)[None]
    return camera_up(R, world_up)[0].numpy().astype(np.float32)


def pose_fitter(
    predictor: Predictor, config: PoseFitConfig | None, num_betas: int
) -> PoseFitter | None:
    """The pose fit of `TrackOptions.pose_fit` for this predictor's body model (None: off)."""
    if config is None:
        return None
    body = getattr(predictor, "body", None)
    if body is None:
        raise ValueError(
            "TrackOptions.pose_fit needs a predictor with a body model (`.body`), "
            f"{type(predictor).__name__} has none"
        )
    return PoseFitter(module_on(body, "cpu"), config, num_betas)  # small solves: CPU numpy


def _input_key(c: PreparedDetection) -> bytes:
    """A digest of everything the network reads from one detection (crop pixels, crop camera,
    landmarks). A blank crop (not cut: the pose comes from the landmarks) is named, not hashed:
    its 196 KB were most of the digest's time at stride 1."""
    h = hashlib.blake2b(digest_size=16)
    h.update(b"blank" if is_blank(c.crop_rgb) else np.ascontiguousarray(c.crop_rgb))
    for a in (c.K_crop, c.landmarks_crop):
        h.update(np.ascontiguousarray(a))
    return h.digest()


class _Group:
    """Crops and predictions of one row group: crops are pooled across frames and predicted
    `batch_size` at a time; the last batch of a group may be smaller."""

    def __init__(
        self,
        predictor: Predictor,
        batch_size: int,
        num_betas: int,
        align: AlignmentConfig | None = None,
        fitter: PoseFitter | None = None,
        up: np.ndarray | None = None,
    ):
        self.predictor, self.batch_size, self.num_betas = predictor, batch_size, num_betas
        self.align = align
        self.fitter = fitter
        self.with_landmarks = accepts_landmarks(predictor)
        # the camera's up direction (3,), for a predictor that reads it; None: not known
        self.up = up if accepts_up(predictor) else None
        self.frames: list[PendingFrame] = []
        self.cut: list[PreparedDetection] = []
        self.poses: list[PoseBatch] = []
        # The answer for an input seen before in this group: a person who stands still keeps
        # their landmarks (gst.track.person_detector, `still_change`), so their network input is
        # the same bytes as in the frame before. Per group, so that a run that starts at a group
        # (a resume, a chunk) predicts what an uninterrupted run predicts.
        self._seen: dict[bytes, PoseBatch] = {}
        self.reused = 0  # rows answered from `_seen`

    def add(self, frame: PendingFrame, cut: list[PreparedDetection]) -> None:
        self.frames.append(frame)
        self.cut.extend(cut)
        while len(self.cut) >= self.batch_size:
            self._predict(self.batch_size)

    def _predict(self, n: int) -> None:
        part = self.cut[:n]
        del self.cut[:n]
        keys = [_input_key(c) for c in part]
        first = {k: i for i, k in reversed(list(enumerate(keys))) if k not in self._seen}
        todo = sorted(first.values())  # each new input once, at its first place
        if todo:
            computed = self._compute([part[i] for i in todo])
            for j, i in enumerate(todo):
                self._seen[keys[i]] = computed.take([j])
        self.reused += n - len(todo)
        self.poses.append(PoseBatch.concat([self._seen[k] for k in keys], self.num_betas))

    def _compute(self, part: list[PreparedDetection]) -> PoseBatch:
        n = len(part)
        crops = np.stack([c.crop_rgb for c in part])
        Ks = np.stack([c.K_crop for c in part])
        lms = np.stack([c.landmarks_crop for c in part])
        extra = {"landmarks": lms} if self.with_landmarks else {}
        if self.up is not None:
            extra["up"] = np.repeat(self.up[None], n, axis=0)
        out = self.predictor(crops, Ks, **extra)
        pose = validate_prediction(out, n)
        if self.align is not None:
            shift = align_translation(pose.joints_cam, Ks, lms, self.align)
            pose.transl_cam = pose.transl_cam + shift
            pose.joints_cam = pose.joints_cam + shift[:, None]
        if self.fitter is not None:
            fit = self.fitter(
                pose.rotmats, pose.betas, pose.transl_cam, pose.joints_cam, Ks, lms,
                crops.shape[1],
            )  # fmt: skip
            pose.rotmats = fit.rotmats.astype(pose.rotmats.dtype)
            pose.transl_cam = fit.transl_cam.astype(pose.transl_cam.dtype)
            pose.joints_cam = fit.joints_cam.astype(pose.joints_cam.dtype)
        if pose.betas.shape[1] != self.num_betas:
            raise ValueError(
                f"predictor returned {pose.betas.shape[1]} betas per person, expected "
                f"num_betas = {self.num_betas}"
            )
        return pose

    def predictions(self) -> PoseBatch:
        if self.cut:
            self._predict(len(self.cut))
        return PoseBatch.concat(self.poses, self.num_betas)


@dataclass(frozen=True)
class VideoRun:
    """What a run over one video is fixed by: its probe, frame range, view and settings."""

    info: VideoInfo
    name: str
    view: TrackingView
    # first frame of the range; groups close on the grid first + k * frames_per_group * stride
    first: int
    end: int | None
    video_json: dict
    calibration: dict
    settings: dict  # everything that determines the output (hashed into the file)
    detector: dict | None = None  # which person detector ran and why (gst.detector)


def plan_run(
    video_path: str | Path,
    *,
    model: dict,
    camera: Camera | None,
    video_name: str | None,
    options: TrackOptions,
    num_betas: int,
    world_up,
    extra_settings: dict | None = None,
    detector_info: dict | None = None,
) -> VideoRun:
    """Probe the video and fix the run's settings (`extra_settings` are added, e.g. chunking;
    `detector_info` says which person detector runs, with its settings)."""
    for key in ("name", "version"):
        if key not in model:
            raise ValueError(f"model info must include '{key}', got keys {sorted(model)}")
    info: VideoInfo = probe_video(video_path)
    if options.fps is not None:
        info = replace(info, fps=float(options.fps))
    name = video_name or info.name
    focal = (
        None
        if camera is not None or options.focal_35mm is None
        else focal_from_35mm(options.focal_35mm, info.width, info.height)
    )
    view = TrackingView.for_video(
        info.width, info.height, camera, video=str(video_path), focal_px=focal
    )
    first, end = frame_range(info, options.start_s, options.end_s)
    video_json = {
        "name": name,
        "file": Path(info.path).name,
        "width": info.width,
        "height": info.height,
        "fps": info.fps,
        "frame_count": info.frame_count,
        "size_bytes": Path(info.path).stat().st_size,
        # the same name and size can be another video (a re-export): its output is not reused
        "content_sha256": content_digest(info.path),
        "first_frame": first,
        "end_frame": end,
        "stride": options.stride,
    }
    calibration = view.to_json()
    settings = {
        "format_version": FORMAT_VERSION,
        "options": options.settings(),
        "model": model,
        "video": video_json,
        "calibration": calibration,
        "num_betas": num_betas,
        "world_up": None if world_up is None else [float(v) for v in world_up],
        "detector": detector_info,
        **(extra_settings or {}),
    }
    return VideoRun(info, name, view, first, end, video_json, calibration, settings, detector_info)


def run_metadata(
    run: VideoRun,
    options: TrackOptions,
    model: dict,
    world_up,
    stats: dict,
    digest: str,
    num_betas: int,
    tracking_extra: dict | None = None,
) -> dict[str, str]:
    """The finished file's schema metadata."""
    return file_metadata(
        fps=run.info.fps,
        model=model,
        calibration=run.calibration,
        axes=_axes_json(run.view.calibrated, world_up),
        video=run.video_json,
        tracking={
            "options": options.settings(),
            "crop": CROP_DESCRIPTION,
            **(tracking_extra or {}),
        },
        detector=run.detector,
        smoothing=asdict(options.smoothing) if options.smoothing else None,
        stats=stats,
        settings_sha256=digest,
        num_betas=num_betas,
    )


@dataclass
class TrackedGroup:
    """One tracked group of frames: its rows and what produced them."""

    table: pa.Table
    next_frame: int  # the frame after the group (where a resumed run continues)
    frames: list[PendingFrame]
    rows: RowSet  # the rows made final by this group (some may be of earlier frames)
    poses: PoseBatch  # the group's predictions (RowSet.source indexes them)
    # the left/right smoother's state after the group's last frame (None: no smoother), saved
    # with the commit so that a resumed run decides the next frames as this run would
    unmirror_state: dict | None = None


def tracked_groups(
    video_path: str | Path,
    run: VideoRun,
    detector: Detector,
    predictor: Predictor,
    session: TrackingSession,
    schema: pa.Schema,
    options: TrackOptions,
    num_betas: int,
    *,
    start_frame: int,
    end_frame: int | None = None,
    on_frame: Callable[[int], None] | None = None,
    unmirror_state: dict | None = None,
) -> Iterator[TrackedGroup]:
    """Track frames [start_frame, end_frame) of the run's range and yield each group as it closes.

    Groups close on the grid `run.first + k * frames_per_group * stride`, whatever the start, so a
    run that starts mid-video (a resume, a chunk) pools exactly the crops an uninterrupted run
    pools for every group it shares with it; batches never span groups, so the predictions are
    the same bytes. `session` is advanced in place; it holds the state as of the yielded group
    until the next one is requested. On a truncated video the last partial group is yielded,
    then VideoTruncatedError is raised. `unmirror_state`: the left/right smoother's state saved
    with the group before `start_frame` (`TrackedGroup.unmirror_state`; None: a fresh start).
    """
    group_span = options.frames_per_group * options.stride
    fitter = pose_fitter(predictor, options.pose_fit, num_betas)
    up = camera_frame_up(run)
    group = _Group(predictor, options.batch_size, num_betas, options.align, fitter, up)

    def close(next_frame: int) -> TrackedGroup:
        nonlocal group
        poses = group.predictions()
        rows = session.track_group(run.view, group.frames, poses)
        table = rows_table(run.view, rows, schema)
        done = TrackedGroup(table, next_frame, group.frames, rows, poses, last_state)
        group = _Group(predictor, options.batch_size, num_betas, options.align, fitter, up)
        return done

    def detect(frame: Frame) -> tuple[Frame, list[Detection]]:
        dets = detector.detect(frame.image, frame.index)
        return frame, [d for d in dets if d.score >= options.min_score]

    def prepare(frame: Frame, dets: list[Detection]) -> tuple[PendingFrame, list]:
        lms = np.full((len(dets), N_LANDMARKS, 3), np.nan, np.float32)
        for i, d in enumerate(dets):
            if d.landmarks is not None:
                lms[i] = d.landmarks
        pixels = needs_pixels(predictor, lms)  # crops whose pose comes from landmarks: not cut
        cut = [
            prepare_detection(run.view, frame.image, d, options.crop_size, bool(p))
            for d, p in zip(dets, pixels, strict=True)
        ]
        pending = PendingFrame(
            frame.index,
            frame.time_s,
            np.array([d.box for d in dets]).reshape(-1, 4),
            np.array([d.score for d in dets], dtype=np.float64),
            np.array([c.appearance for c in cut]).reshape(len(dets), DESCRIPTOR_SIZE),
            lms,
        )
        return pending, cut

    # Three threads when prefetching: decoding; the person detector; crops, the network and the
    # tracker (the detector is the heaviest per frame, so the crops are cut beside the network).
    frames = iter_frames(
        video_path,
        stride=options.stride,
        start_s=options.start_s,
        end_s=options.end_s,
        start_frame=start_frame,
        end_frame=end_frame,
        prefetch=options.prefetch,
        fps=options.fps,
    )
    detected = (detect(f) for f in frames)
    if options.prefetch > 0:
        detected = background(detected, options.prefetch)
    # each person's left/right labels made continuous (gst.track.mirror): prepared frames wait
    # `lag_s` for their decision; their images do not (the crops are cut first)
    smoother = None
    if options.unmirror is not None:
        smoother = LabelSmoother(options.unmirror, options.stride / run.info.fps, with_state=True)
        if unmirror_state is not None:
            smoother.load_state_dict(unmirror_state)
    last_state = unmirror_state

    def decided(released: list) -> list[tuple[PendingFrame, list, dict, int]]:
        """Frames with their labels put right, the smoother's state after each, and how many
        detections were exchanged (counted when the frame joins a group, so that a committed
        group's stats cover exactly the committed frames)."""
        out = []
        for (pending, cut), flags, state in released:
            for i in np.flatnonzero(flags):
                pending.landmarks[i] = pending.landmarks[i][BLAZEPOSE_MIRROR]
                cut[i].landmarks_crop = cut[i].landmarks_crop[BLAZEPOSE_MIRROR]
            out.append((pending, cut, state, int(np.count_nonzero(flags))))
        return out

    def release(pending: PendingFrame, cut: list) -> list[tuple[PendingFrame, list, dict, int]]:
        if smoother is None:
            return [(pending, cut, None, 0)]
        people = [lm if np.isfinite(lm).any() else None for lm in pending.landmarks]
        return decided(smoother.push((pending, cut), people))

    def flush() -> list[tuple[PendingFrame, list, dict, int]]:
        return [] if smoother is None else decided(smoother.flush())

    last_index = None

    def add(
        pending: PendingFrame, cut: list, state: dict | None, exchanged: int
    ) -> Iterator[TrackedGroup]:
        nonlocal last_index, last_state
        group.add(pending, cut)
        session.stats["landmarks_exchanged"] += exchanged
        last_index, last_state = pending.index, state
        if on_frame is not None:
            on_frame(pending.index)
        next_frame = pending.index + options.stride
        if (next_frame - run.first) % group_span == 0:
            yield close(next_frame)

    def finish() -> Iterator[TrackedGroup]:
        """The frames still waiting for the smoother, then the last, partial group."""
        for released in flush():
            yield from add(*released)
        if group.frames:
            yield close(last_index + options.stride)

    try:
        for frame, dets in detected:
            for released in release(*prepare(frame, dets)):
                yield from add(*released)
    except VideoTruncatedError:  # the frames before the damage are decided and kept
        yield from finish()
        raise
    finally:
        # both prefetch stages: on an error the exception's traceback holds the generators in
        # a cycle, so a decode thread and its capture would otherwise live until the next gc
        for stage in (detected, frames):
            close_stage = getattr(stage, "close", None)
            if close_stage is not None:
                close_stage()
    yield from finish()


def track_video(
    video_path: str | Path,
    out_root: str | Path,
    detector: Detector,
    predictor: Predictor,
    *,
    model: dict,
    camera: Camera | None = None,
    video_name: str | None = None,
    options: TrackOptions | None = None,
    num_betas: int = 10,
    world_up=None,
    resume: bool = True,
    staging_root: str | Path | None = None,
    on_frame: Callable[[int], None] | None = None,
    on_extra: Callable[[int, int, dict], None] | None = None,
    detector_info: dict | None = None,
    detections_cache: str | Path | None = None,
) -> TrackResult:
    """Track every person in `video_path` and write <out_root>/video=<name>/tracks.parquet.

    `model` must hold at least "name" and "version" (recorded in the file). `camera` is the
    video's calibrated camera, or None for the default camera (see gst.data.camera_view). With
    `resume`, a partial run with the same settings is continued and a finished file with the same
    settings is returned as is; without it, earlier output for this video is replaced. Raises
    VideoError (naming the file) for unreadable video; on a truncated video the frames before the
    damage are committed first (valid Parquet in the staging folder), then the error is raised.
    `detector_info` (which person detector runs and why) is recorded as `gst.detector` and in
    the settings digest. `on_frame(frame)` is called for every processed frame (progress bars).
    With `detections_cache` (a folder) and `detector_info`, a run from the first frame of a video
    of known length replays the detections kept there by an earlier run with the same video,
    detector and frames, or keeps its own for the next (gst.track.detection_cache).
    `on_extra(frame, person_id, extra)` receives, for every written row, the predictor's outputs
    beyond the body (e.g. Gaussians for a per-track splat), after the row group holding it is
    committed; frames committed by an earlier, interrupted run are not replayed.
    Partial work lives in `staging_root` (default: the hidden sibling .<out_root name>.inprogress),
    never inside `out_root`, so readers of the dataset only ever see finished videos.
    """
    t0 = time.perf_counter()
    options = options or TrackOptions()
    run = plan_run(
        video_path,
        model=model,
        camera=camera,
        video_name=video_name,
        options=options,
        num_betas=num_betas,
        world_up=world_up,
        detector_info=detector_info,
    )
    writer = TrackWriter(out_root, run.name, tracks_schema(num_betas), run.settings, staging_root)
    if resume and writer.finished_digest() == writer.digest:
        writer.discard_staging()  # left behind if a run died between finishing and cleaning up
        stats = json.loads(pq.read_schema(writer.final_path).metadata[b"gst.stats"])
        return TrackResult(
            writer.final_path,
            stats["rows"],
            stats["frames"],
            stats["persons"],
            None,
            time.perf_counter() - t0,
            DETECTIONS_NOT_NEEDED,
        )
    session = TrackingSession(options.tracker, options.smoothing)
    point = writer.start(resume=resume)
    start_frame, resumed_from, seconds_before = run.first, None, 0.0
    if point is not None:
        session.load_state_dict(point.state)
        start_frame = resumed_from = point.next_frame
        # time spent by the runs this one resumes (kept beside the state, never in the output)
        seconds_before = float(point.state.get("elapsed_s", 0.0))
    detector, keep_detections, detections = _with_kept_detections(
        detector, detections_cache, video_path, run, start_frame, options.stride
    )
    for g in tracked_groups(
        video_path,
        run,
        detector,
        predictor,
        session,
        writer.schema,
        options,
        num_betas,
        start_frame=start_frame,
        on_frame=on_frame,
        unmirror_state=None if point is None else point.state.get("unmirror"),
    ):
        elapsed = seconds_before + time.perf_counter() - t0
        state = {**session.state_dict(), "unmirror": g.unmirror_state, "elapsed_s": elapsed}
        writer.commit(g.table, g.next_frame, state)
        if on_extra is not None and g.poses.extra:
            _replay_extras(g, on_extra)
    if keep_detections is not None and not keep_detections():
        detections = "run"  # they could not be kept: the run's own result stands
    stats = {**session.stats, "persons": session.tracker.next_id}
    # detections of a person still waiting for `min_hits` when the video ends never get a row:
    # counted with the other short flickers, so that detections = rows + the dropped counts
    stats["dropped_low_score"] += len(session.pending)
    if stats["frames"] == 0 and run.first > 0 and resumed_from is None:
        # a stream that holds no frame count (raw streams, browser WebM): the range could not
        # be checked against its length before decoding, and the file itself was blamed
        raise VideoError(
            f"{video_path}: no frame at or after the start, frame {run.first} "
            f"({options.start_s} s): the start lies past the end of the video (its container "
            "gives no frame count to check it against before decoding); nothing was written"
        )
    if stats["frames"] == 0:  # an empty file would read as a finished video in which nobody moved
        raise VideoError(
            f"{video_path}: no frame could be decoded (an empty or unreadable video stream); "
            "nothing was written"
        )
    meta = run_metadata(run, options, model, world_up, stats, writer.digest, num_betas)
    path = writer.finalize(meta, options.row_group_rows)
    return TrackResult(
        path,
        stats["rows"],
        stats["frames"],
        stats["persons"],
        resumed_from,
        seconds_before + time.perf_counter() - t0,
        detections,
    )


def _with_kept_detections(
    detector: Detector,
    cache: str | Path | None,
    video_path: str | Path,
    run: VideoRun,
    start_frame: int,
    stride: int,
) -> tuple[Detector, Callable[[], bool] | None, str]:
    """The detector to run (the kept detections replayed, or the given one recording them), what
    saves the recording at the end (None: nothing to save; it returns False where it could
    not), and which it was (`TrackResult.detections`)."""
    if cache is None or run.detector is None or run.end is None or start_frame != run.first:
        return detector, None, "run"
    path = Path(cache) / detections_key(video_path, run.detector, run.first, stride)
    kept = load_detections(path, run.first, stride, run.end)
    if kept is not None:
        log.info("%s: person detections replayed from %s", run.name, path)
        return kept, None, "replayed"
    recording = RecordingDetector(detector)

    def keep() -> bool:
        try:
            recording.save(path, run.end)
        except OSError as exc:  # a full disk or a read-only cache: the tracks do not need it
            log.warning("%s: person detections not kept in %s (%s)", run.name, path, exc)
            return False
        return True

    return recording, keep, "run and kept"


def _replay_extras(g: TrackedGroup, on_extra: Callable[[int, int, dict], None]) -> None:
    """Extras of the group's rows, in the rows' order (held rows of earlier groups have none)."""
    r = g.rows
    for i in np.lexsort((r.person_id, r.frame)):
        if r.source[i] >= 0:
            on_extra(
                int(r.frame[i]),
                int(r.person_id[i]),
                {k: np.asarray(v)[r.source[i]] for k, v in g.poses.extra.items()},
            )
