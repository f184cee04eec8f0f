"""Track one video end to end: decode, detect, crop, predict in batches, track, smooth, write.

Work proceeds in groups of `frames_per_group` processed frames. Within a group, crops from
consecutive frames are pooled and predicted `batch_size` at a time; then the group's frames are
tracked in order and its rows are committed as one row group, together with the tracker and
smoother state. A rerun resumes after the last committed group and, because batches never span
groups, reproduces an uninterrupted run byte for byte.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.spatial.transform import Rotation

from calibration import Camera
from gst.track.appearance import DESCRIPTOR_SIZE, colour_histogram, core_region
from gst.track.background import background
from gst.track.crop import CropWindow, cut_crop, cut_undistorted_crop
from gst.track.detection import Detection, Detector
from gst.track.predictor import PoseBatch, Predictor, validate_prediction
from gst.track.schema import FORMAT_VERSION, file_metadata, tracks_schema
from gst.track.smoothing import OneEuroConfig, PoseSmoother
from gst.track.tracker import Observation, Tracker, TrackerConfig
from gst.track.video import (
    Frame,
    VideoInfo,
    VideoTruncatedError,
    frame_range,
    iter_frames,
    probe_video,
)
from gst.track.view import TrackingView
from gst.track.writer import TrackWriter


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
    prefetch: int = 4  # frames decoded, detected and cropped ahead in a thread (0: inline); same output
    row_group_rows: int = 65536  # row-group size of the finished file

    def __post_init__(self):
        for name in ("stride", "crop_size", "batch_size", "frames_per_group", "row_group_rows"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrackOptions.{name} must be >= 1, got {getattr(self, name)}")

    def settings(self) -> dict:
        """What determines the output (prefetch does not)."""
        d = asdict(self)
        d.pop("prefetch")
        return d


CROP_DESCRIPTION = "HMR2: square side 1.2 x max(w, h) of the box, centred, resized, zero padding outside the frame"


@dataclass(frozen=True)
class TrackResult:
    path: Path
    rows: int
    frames: int  # processed frames, this run and earlier runs it resumed
    persons: int
    resumed_from_frame: int | None
    seconds: float


def _camera_json(cam: Camera, calibrated: bool) -> dict:
    return {"calibrated": calibrated, "name": cam.name, "width": cam.width, "height": cam.height,
            "K": cam.K.tolist(), "dist": cam.dist.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(),
            "meta": {k: str(v) for k, v in cam.meta.items()}}


def _axes_json(calibrated: bool, world_up) -> dict:
    axes = {"camera": "OpenCV: x right, y down, z forward (metres)",
            "joints3d": "world" if calibrated else "camera",
            "body": "SMPL: global_orient rotates the body frame (x left, y up, z forward) into joints3d's frame"}
    if calibrated:
        axes["world"] = {"description": "the rig's world frame (metres), X_cam = R X_world + t",
                         "up": None if world_up is None else [float(v) for v in world_up]}
    return axes


@dataclass
class _Pending:
    """One processed frame's detections while its group is being assembled."""

    index: int
    time_s: float
    boxes: np.ndarray  # (n, 4) raw-frame boxes
    scores: np.ndarray  # (n,)
    appearance: np.ndarray  # (n, D)


class _Group:
    """Crops and predictions of one row group."""

    def __init__(self, predictor: Predictor, batch_size: int, num_betas: int):
        self.predictor, self.batch_size, self.num_betas = predictor, batch_size, num_betas
        self.frames: list[_Pending] = []
        self.crops: list[np.ndarray] = []
        self.Ks: list[np.ndarray] = []
        self.poses: list[PoseBatch] = []

    def add(self, frame: _Pending, crops: list[np.ndarray], Ks: list[np.ndarray]) -> None:
        self.frames.append(frame)
        self.crops.extend(crops)
        self.Ks.extend(Ks)
        while len(self.crops) >= self.batch_size:
            self._predict(self.batch_size)

    def _predict(self, n: int) -> None:
        crops, Ks = np.stack(self.crops[:n]), np.stack(self.Ks[:n])
        del self.crops[:n], self.Ks[:n]
        pose = validate_prediction(self.predictor(crops, Ks), n)
        if pose.betas.shape[1] != self.num_betas:
            raise ValueError(f"predictor returned {pose.betas.shape[1]} betas per person, expected "
                             f"num_betas = {self.num_betas}")
        self.poses.append(pose)

    def predictions(self) -> PoseBatch:
        if self.crops:
            self._predict(len(self.crops))
        return PoseBatch.concat(self.poses, self.num_betas)


def _cut(view: TrackingView, frame_bgr: np.ndarray, det: Detection, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(RGB crop, K_crop, appearance histogram) of one detection."""
    window: CropWindow = view.window(det.box, size)
    crop_bgr, K_crop = view.crop(frame_bgr, window)
    crop_rgb = cv2.cvtColor(crop_bgr, cv2.COLOR_BGR2RGB)
    box = view.model_box(det.box)
    box_in_crop = (box - [window.x0, window.y0, window.x0, window.y0]) * window.scale
    if det.mask is not None:
        m = np.asarray(det.mask, dtype=np.uint8)
        if m.shape != frame_bgr.shape[:2]:
            raise ValueError(f"detection mask has shape {m.shape}, expected the frame's {frame_bgr.shape[:2]}")
        mc = (cut_undistorted_crop(m, view.camera, window, cv2.INTER_NEAREST) if view.has_distortion
              else cut_crop(m, window, cv2.INTER_NEAREST))
        rows, cols = core_region(size, box_in_crop, 0.0, 0.0)
        hist = colour_histogram(crop_rgb[rows, cols], (mc[rows, cols] > 0).astype(np.uint8))
    else:
        rows, cols = core_region(size, box_in_crop)
        hist = colour_histogram(crop_rgb[rows, cols])
    return crop_rgb, K_crop, hist


def _rotvec(R: np.ndarray) -> np.ndarray:
    shape = R.shape[:-2]
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*shape, 3)


def _rows(view: TrackingView, group: list[_Pending], ids: list[list[int]], poses: PoseBatch,
          keep: np.ndarray, schema: pa.Schema) -> pa.Table:
    """The group's rows, sorted by frame then person_id; `keep` marks detections that got an id."""
    frame_of = np.concatenate([[f.index] * len(f.scores) for f in group]).astype(np.int64) if group else np.zeros(0, np.int64)
    time_of = np.concatenate([[f.time_s] * len(f.scores) for f in group]) if group else np.zeros(0)
    boxes = np.concatenate([f.boxes for f in group]) if group else np.zeros((0, 4))
    scores = np.concatenate([f.scores for f in group]) if group else np.zeros(0)
    pid = np.concatenate([np.asarray(i, dtype=np.int64) for i in ids]) if ids else np.zeros(0, np.int64)
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((pid[sel], frame_of[sel]))]
    p = poses.take(sel)
    n = len(sel)
    go_cam = _rotvec(p.rotmats[:, 0])
    body_pose = _rotvec(p.rotmats[:, 1:])
    joints_cam = p.joints_cam
    if view.calibrated:
        joints3d = view.to_world(joints_cam)
        go = _rotvec(view.rotation_to_world(p.rotmats[:, 0]))
        # SMPL rotates about the root joint J0: choose transl_world so that the body model with
        # (global_orient world, transl_world) reproduces the world joints.
        rest_root = joints_cam[:, 0] - p.transl_cam
        transl_world = joints3d[:, 0] - rest_root
    else:
        joints3d, go, transl_world = joints_cam, go_cam, None
    joints2d = view.project(joints_cam)

    def fixed(a: np.ndarray, name: str) -> pa.FixedSizeListArray:
        width = schema.field(name).type.list_size
        flat = np.ascontiguousarray(a, dtype=np.float32).reshape(n, width)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), width)

    cols = {
        "frame": pa.array(frame_of[sel]), "time_s": pa.array(time_of[sel], pa.float64()),
        "person_id": pa.array(pid[sel]), "bbox": fixed(boxes[sel], "bbox"),
        "score": pa.array(scores[sel].astype(np.float32)), "global_orient": fixed(go, "global_orient"),
        "global_orient_cam": fixed(go_cam, "global_orient_cam"), "body_pose": fixed(body_pose, "body_pose"),
        "betas": fixed(p.betas, "betas"), "transl_cam": fixed(p.transl_cam, "transl_cam"),
        "transl_world": (fixed(transl_world, "transl_world") if transl_world is not None
                         else pa.nulls(n, schema.field("transl_world").type)),
        "joints3d": fixed(joints3d, "joints3d"), "joints2d": fixed(joints2d, "joints2d"),
    }
    return pa.Table.from_arrays([cols[f.name].cast(f.type) for f in schema], schema=schema)


class _Session:
    """Tracker, smoother and counters: everything a resumed run must restore."""

    def __init__(self, options: TrackOptions):
        self.tracker = Tracker(options.tracker)
        self.smoother = PoseSmoother(options.smoothing) if options.smoothing else None
        self.stats = {"frames": 0, "rows": 0, "detections": 0, "dropped_nonfinite": 0, "dropped_low_score": 0}

    def state_dict(self) -> dict:
        return {"tracker": self.tracker.state_dict(), "smoother": self.smoother.state_dict() if self.smoother else {},
                "stats": dict(self.stats)}

    def load_state_dict(self, state: dict) -> None:
        self.tracker.load_state_dict(state["tracker"])
        if self.smoother:
            self.smoother.load_state_dict(state["smoother"])
        self.stats = dict(state["stats"])

    def track_group(self, view: TrackingView, group: list[_Pending], poses: PoseBatch) -> tuple[list[list[int]], PoseBatch, np.ndarray]:
        """Ids for every detection (-1: none), smoothed poses, and which detections to keep."""
        finite = poses.finite()
        ids: list[list[int]] = []
        keep = np.zeros(len(poses), bool)
        out = PoseBatch(poses.rotmats.copy(), poses.betas.copy(), poses.transl_cam.copy(), poses.joints_cam.copy(), {})
        k = 0
        for f in group:
            n = len(f.scores)
            idx = np.arange(k, k + n)[finite[k:k + n]]
            self.stats["dropped_nonfinite"] += int(n - len(idx))
            pelvis = out.joints_cam[idx, 0]
            pos = view.to_world(pelvis) if view.calibrated else pelvis
            obs = [Observation(f.boxes[j - k], pos[i], f.appearance[j - k], float(f.scores[j - k]))
                   for i, j in enumerate(idx)]
            got = self.tracker.update(f.time_s, obs)
            frame_ids = [-1] * n
            for j, pid in zip(idx, got, strict=True):
                frame_ids[j - k] = pid
                if pid >= 0:
                    keep[j] = True
                    if self.smoother:
                        s = self.smoother(pid, f.time_s, {q: getattr(out, q)[j] for q in
                                                          ("rotmats", "betas", "transl_cam", "joints_cam")})
                        for q, v in s.items():
                            getattr(out, q)[j] = v
                else:
                    self.stats["dropped_low_score"] += 1
            if self.smoother:
                self.smoother.retain({t.id for t in self.tracker.tracks})
            ids.append(frame_ids)
            k += n
        self.stats["frames"] += len(group)
        self.stats["detections"] += len(poses)
        self.stats["rows"] += int(keep.sum())
        return ids, out, keep


def track_video(video_path: str | Path, out_root: str | Path, detector: Detector, predictor: Predictor, *,
                model: dict, camera: Camera | None = None, video_name: str | None = None,
                options: TrackOptions | None = None, num_betas: int = 10, world_up=None, resume: bool = True,
                staging_root: str | Path | None = None, on_frame: Callable[[int], None] | None = None,
                on_extra: Callable[[int, int, dict], None] | None = None) -> TrackResult:
    """Track every person in `video_path` and write <out_root>/video=<name>/tracks.parquet.

    `model` must hold at least "name" and "version" (recorded in the file). `camera` is the
    video's calibrated camera, or None for the default camera (see gst.track.view). With
    `resume`, a partial run with the same settings is continued and a finished file with the same
    settings is returned as is; without it, earlier output for this video is replaced. Raises
    VideoError (naming the file) for unreadable video; on a truncated video the frames before the
    damage are committed first (valid Parquet in the staging folder), then the error is raised.
    `on_frame(frame)` is called for every processed frame (progress bars). `on_extra(frame,
    person_id, extra)` receives, for every written row, the predictor's outputs beyond the body
    (e.g. Gaussians for a per-track splat), after the row group holding it is committed; frames
    committed by an earlier, interrupted run are not replayed.
    Partial work lives in `staging_root` (default: the hidden sibling .<out_root name>.inprogress),
    never inside `out_root`, so readers of the dataset only ever see finished videos.
    """
    t0 = time.perf_counter()
    options = options or TrackOptions()
    for key in ("name", "version"):
        if key not in model:
            raise ValueError(f"model info must include '{key}', got keys {sorted(model)}")
    info: VideoInfo = probe_video(video_path)
    name = video_name or info.name
    view = TrackingView.for_video(info.width, info.height, camera, video=str(video_path))
    first, end = frame_range(info, options.start_s, options.end_s)
    video_json = {"name": name, "file": Path(info.path).name, "width": info.width, "height": info.height,
                  "fps": info.fps, "frame_count": info.frame_count, "size_bytes": Path(info.path).stat().st_size,
                  "first_frame": first, "end_frame": end, "stride": options.stride}
    calibration = _camera_json(view.camera, view.calibrated)
    settings = {"format_version": FORMAT_VERSION, "options": options.settings(), "model": model,
                "video": video_json, "calibration": calibration, "num_betas": num_betas,
                "world_up": None if world_up is None else [float(v) for v in world_up]}
    writer = TrackWriter(out_root, name, tracks_schema(num_betas), settings, staging_root)
    if resume and writer.finished_digest() == writer.digest:
        writer.discard_staging()  # left behind if a run died between finishing and cleaning up
        stats = json.loads(pq.read_schema(writer.final_path).metadata[b"gst.stats"])
        return TrackResult(writer.final_path, stats["rows"], stats["frames"], stats["persons"], None,
                           time.perf_counter() - t0)
    session = _Session(options)
    point = writer.start(resume=resume)
    start_frame, resumed_from = first, None
    if point is not None:
        session.load_state_dict(point.state)
        start_frame = resumed_from = point.next_frame
    group = _Group(predictor, options.batch_size, num_betas)

    def commit(next_frame: int) -> None:
        nonlocal group
        poses = group.predictions()
        ids, smoothed, keep = session.track_group(view, group.frames, poses)
        table = _rows(view, group.frames, ids, smoothed, keep, writer.schema)
        writer.commit(table, next_frame, session.state_dict())
        if on_extra is not None and poses.extra:
            frame_of = np.array([f.index for f in group.frames for _ in range(len(f.scores))], dtype=np.int64)
            flat_ids = np.array([i for frame_ids in ids for i in frame_ids], dtype=np.int64)
            kept = np.flatnonzero(keep)
            for j in kept[np.lexsort((flat_ids[kept], frame_of[kept]))]:  # the rows' order
                on_extra(int(frame_of[j]), int(flat_ids[j]), {k: np.asarray(v)[j] for k, v in poses.extra.items()})
        group = _Group(predictor, options.batch_size, num_betas)

    def prepare(frame: Frame) -> tuple[_Pending, list[np.ndarray], list[np.ndarray]]:
        dets = [d for d in detector.detect(frame.image, frame.index) if d.score >= options.min_score]
        cut = [_cut(view, frame.image, d, options.crop_size) for d in dets]
        pending = _Pending(frame.index, frame.time_s, np.array([d.box for d in dets]).reshape(-1, 4),
                           np.array([d.score for d in dets], dtype=np.float64),
                           np.array([c[2] for c in cut]).reshape(len(dets), DESCRIPTOR_SIZE))
        return pending, [c[0] for c in cut], [c[1] for c in cut]

    frames = iter_frames(video_path, stride=options.stride, start_s=options.start_s, end_s=options.end_s,
                         start_frame=start_frame)
    prepared = (prepare(f) for f in frames)
    if options.prefetch > 0:
        prepared = background(prepared, options.prefetch)
    last_index = None
    try:
        for pending, crops, Ks in prepared:
            group.add(pending, crops, Ks)
            last_index = pending.index
            if on_frame is not None:
                on_frame(pending.index)
            if len(group.frames) == options.frames_per_group:
                commit(pending.index + options.stride)
    except VideoTruncatedError:
        if group.frames:
            commit(last_index + options.stride)
        raise
    finally:
        close = getattr(prepared, "close", None)
        if close is not None:
            close()
    if group.frames:
        commit(last_index + options.stride)
    stats = {**session.stats, "persons": session.tracker.next_id}
    meta = file_metadata(
        fps=info.fps, model=model, calibration=calibration, axes=_axes_json(view.calibrated, world_up),
        video=video_json, tracking={"options": options.settings(), "crop": CROP_DESCRIPTION},
        smoothing=asdict(options.smoothing) if options.smoothing else None, stats=stats,
        settings_sha256=writer.digest, num_betas=num_betas)
    path = writer.finalize(meta, options.row_group_rows)
    return TrackResult(path, stats["rows"], stats["frames"], stats["persons"], resumed_from,
                       time.perf_counter() - t0)
