"""The whole extraction of one scene: videos + rig -> crop store + report.

Four phases, resumable through a work folder next to the store (`<store>.work/`):

1. masks (`masks`, per camera, parallel): learn the background, label foreground blobs per
   frame at a reduced "work" resolution, or person instances with their landmarks (BlazePose),
   or take external masks/boxes instead.
2. association (all cameras, sequential in time): by keypoints (`keypoint_association`:
   landmarks matched across views -> 3D people -> ids, each person looked at again with the
   others painted out) when BlazePose is installed, else by the visual hull (`association`:
   hull -> people -> ids); both write per-camera person label images. The log says which ran.
3. crops (`crops`, per camera, parallel): undistorted square crops of image and mask with their
   own intrinsics, into a per-camera part store compressed as the scene store is; scored
   against truth masks when given.
4. merge (`gst.data.store.merge_part`): the part stores are appended to the scene store frame
   by frame (crops and masks as their compressed chunks), then the Parquet index is written and
   the store marked complete.

Per-camera work lives in module-level functions taking one picklable job, so `executor_map`
can be a process pool's `map`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from calibration import Camera, Rig
from calibration.camera import fit_rig_to_frames
from gst.atomic import atomic_write_json
from gst.data.background import BackgroundConfig
from gst.data.evaluate import CropTruth, association_accuracy
from gst.data.external import ExternalDetections, find_mask_file, read_external
from gst.data.extract.association import AssociationSummary, associate_scene
from gst.data.extract.crops import CropJob, extract_camera_crops, visible_truth_views
from gst.data.extract.keypoint_association import associate_scene_keypoints
from gst.data.extract.masks import MaskJob, compute_camera_masks
from gst.data.extract.options import (
    WORK_MAX_SIDE,
    CameraReport,
    ExtractError,
    ExtractOptions,
    ExtractReport,
    SourceScore,
)
from gst.data.keypoints.people import CrowdConfig
from gst.data.store import CropBatch, CropStore, CropStoreWriter, merge_part
from gst.detect.blazepose import import_litert
from gst.detect.persons import SegmenterConfig
from gst.detect.weights import BlazePoseModelsMissing, model_paths
from gst.video import (
    VideoError,
    VideoInfo,
    check_videos,
    differing_rates,
    file_identity,
    probe_video,
    scaled_size,
)
from synth.truth import has_scene_truth

log = logging.getLogger("gst.data")


def _fingerprint(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _camera_signature(cam: Camera) -> list:
    return [
        cam.name,
        cam.K.round(9).tolist(),
        cam.dist.round(12).tolist(),
        cam.R.round(12).tolist(),
        cam.t.round(12).tolist(),
        cam.width,
        cam.height,
    ]


def _resolve_truth(truth: Path | str | None) -> Path | None:
    if truth is None:
        return None
    p = Path(truth)
    if (p / "masks").is_dir():
        p = p / "masks"
    if not p.is_dir():
        raise ExtractError(
            f"truth masks folder {p} does not exist (expected <scene>/truth or <scene>/truth/masks)"
        )
    return p


def association_method(
    options: ExtractOptions, external: ExternalDetections | None
) -> tuple[str, str]:
    """('keypoints' or 'hull', why) for these options: keypoints when asked or 'auto' and the
    detect extra and the BlazePose models are there; the hull for external masks or boxes."""
    asked = options.association_method
    if external is not None and (external.mask_files or external.boxes):
        if asked == "keypoints":
            raise ExtractError(
                "association_method 'keypoints' needs BlazePose instances on every camera; "
                "external masks or boxes were given (use 'hull' or 'auto')"
            )
        return "hull", "external masks or boxes were given"
    if asked == "hull":
        return "hull", "association_method 'hull'"
    try:
        import_litert()
        model_paths(options.persons_models_dir)
    except (ImportError, BlazePoseModelsMissing) as exc:
        if asked == "keypoints":
            raise ExtractError(f"association_method 'keypoints': {exc}") from exc
        return "hull", f"BlazePose is not available ({exc})"
    return "keypoints", f"association_method '{asked}' and BlazePose is installed"


def _map(executor_map, fn, items, description):
    if executor_map is None:
        return [fn(x) for x in items]
    return list(executor_map(fn, items, description))


@dataclass
class ExtractPlan:
    """Everything the phases need, checked up front: cameras in rig order, frames, sizes,
    external inputs, settings and the work folder."""

    videos: dict[str, Path]
    rig: Rig
    out_h5: Path
    names: list[str]
    infos: dict[str, VideoInfo]
    n_frames: int
    frames: list[int]
    sizes: dict[str, tuple[int, int]]
    work_sizes: dict[str, tuple[int, int]]
    crop_size: int
    scale: float
    frame_stride: int
    background: BackgroundConfig
    options: ExtractOptions
    external: ExternalDetections | None
    plates: dict[str, Path]
    truth_files: dict[str, Path | None]
    settings: dict
    work: Path
    association: str = "hull"  # 'keypoints' or 'hull'
    work_key: str = ""  # fingerprint of the inputs and settings the work folder holds

    @property
    def frame_set(self) -> set[int]:
        return set(self.frames)

    @property
    def fps(self) -> float:
        if self.options.fps is not None:  # the scene's, where the headers are not trusted
            return float(self.options.fps)
        # the first camera whose container gives a rate (`_check_frame_rates` held them to one):
        # the first camera's alone, unstated, timed 60 frames/s videos at 30
        rates = [self.infos[n].fps for n in self.names if self.infos[n].fps > 0]
        return rates[0] if rates else 30.0  # unknown rate: assume 30


@dataclass
class PhaseOutcome:
    """What the phases of this run produced (nothing when the store was already complete)."""

    per_camera: dict[str, CameraReport]
    pairs_resumed: int
    skipped_cameras: list[str] = field(default_factory=list)
    truth_rows: list[CropTruth] = field(default_factory=list)
    truth_views: int = 0
    truth_missed: int = 0
    visible_views: int = 0
    visible_missed: int = 0
    summary: AssociationSummary | None = None
    timings: dict[str, float] = field(default_factory=dict)


def _check_frame_rates(infos: dict[str, VideoInfo]) -> None:
    """Refuse videos whose containers give different frame rates: with equal frame counts they
    cover different spans of time, so frame i is not one instant in every camera (the first
    camera's rate timed them all, silently)."""
    detail = differing_rates(infos)
    if detail:
        raise VideoError(
            f"videos have different frame rates across cameras ({detail} frames/s); expected "
            "synchronised videos of one rate (where the headers are wrong, give the rate: "
            "scenes.NAME.fps or ExtractOptions(fps=...))"
        )


def plan_extraction(
    videos: dict[str, Path],
    rig: Rig,
    out_h5: Path,
    *,
    crop_size: int,
    scale: float,
    frame_stride: int,
    method: str,
    external: Path | str | ExternalDetections | None,
    truth: Path | str | None,
    options: ExtractOptions,
) -> ExtractPlan:
    """Validate the inputs and settings, and name the work folder (`prepare_work` readies it,
    once the store has accepted these settings)."""
    opts = options
    if crop_size < 16:
        raise ExtractError(f"crop_size must be >= 16 pixels, got {crop_size}")
    if scale < 1.0:
        raise ExtractError(f"scale must be >= 1 (the crop surrounds the person box), got {scale}")
    if frame_stride < 1:
        raise ExtractError(f"frame_stride must be >= 1, got {frame_stride}")
    bg_cfg = BackgroundConfig(**{**asdict(opts.background), "method": method})
    videos = {str(k): Path(v) for k, v in videos.items()}
    infos = check_videos(videos, rig.names)
    if opts.fps is None:  # the scene's rate, when given, overrides headers not trusted
        _check_frame_rates(infos)
    elif rates := differing_rates(infos):  # taken as wrong headers, but said: it may be a camera
        log.warning(
            "extract: the videos' headers give different frame rates (%s frames/s); every camera "
            "is timed at the scene's %g frames/s (scenes.NAME.fps) and frame i is taken for one "
            "instant in all of them", rates, float(opts.fps),
        )  # fmt: skip
    if opts.fps is None and not any(i.fps > 0 for i in infos.values()):
        # Said here, at the first stage: fuse (TRC/C3D rates, its temporal prior) refuses a
        # capture with no known rate, so a user learns of it before a long extraction, not after.
        log.warning(
            "extract: no video header gives a frame rate (%s); the person tracker is timed at "
            "30 frames/s, and the fuse stage will refuse the scene: give its rate "
            "(scenes.NAME.fps)", ", ".join(sorted(infos)),
        )  # fmt: skip
    names = [n for n in rig.names if n in videos]  # rig order
    rig, _ = fit_rig_to_frames(rig, infos, opts.frame_size_tolerance)
    n_frames = next(iter(infos.values())).frames
    frames = list(range(0, n_frames, frame_stride))
    sizes = {n: (infos[n].width, infos[n].height) for n in names}
    ext = (
        external
        if isinstance(external, ExternalDetections) or external is None
        else read_external(external, names)
    )
    if ext is not None:
        ext.validate(sizes, n_frames)
    plates = {str(k): Path(v) for k, v in (opts.background_videos or {}).items()}
    for n, p in plates.items():
        if n not in videos:
            raise VideoError(
                f"background video {p} is for camera '{n}', which has no video (cameras: {names})"
            )
        info = probe_video(p, n, strict=True)
        if (info.width, info.height) != sizes[n]:
            raise VideoError(
                f"camera '{n}' background video {p}: frames are {info.width}x{info.height}, "
                f"the camera's video is {sizes[n][0]}x{sizes[n][1]}"
            )
    # (not `method`, the background's: the store's setting.method held the association)
    association, why = association_method(opts, ext)
    if association == "hull" and len(names) < 2 and not (ext is not None and ext.global_ids):
        # checked before anything is written (phase 2 refused it after phase 1's masks, leaving
        # an incomplete store, and its words blamed cameras that saw nobody)
        raise ExtractError(
            f"the visual hull ({why}) associates people across the videos of at least two "
            f"cameras; got {names} (give more cameras' videos, or external masks with "
            "global_ids)"
        )
    log.info("extract: %s association (%s)", association, why)
    if association == "keypoints":
        # Person instances with landmarks on every camera (phase 1), matched by keypoints.
        persons = opts.persons or SegmenterConfig(
            detect_every=opts.person_detect_every, zoom=opts.person_zoom
        )
        opts = replace(opts, persons=persons)
    elif opts.persons is not None:
        model_paths(opts.persons_models_dir)  # fail now, with the fix, rather than in a worker
        # Learned masks are person instances: split hull components along them.
        opts = replace(opts, association=replace(opts.association, instance_split=True))
    truth_dir = _resolve_truth(truth)
    truth_files = {n: find_mask_file(truth_dir, n) for n in names} if truth_dir else {}

    def work_size(n: str) -> tuple[int, int]:
        w, h = sizes[n]
        ws = opts.work_scale if opts.work_scale else min(1.0, WORK_MAX_SIDE / max(w, h))
        if not 0 < ws <= 1:
            raise ExtractError(f"work_scale must be in (0, 1], got {ws}")
        return scaled_size(w, h, ws)

    work_sizes = {n: work_size(n) for n in names}
    volume = opts.volume
    settings = {
        "scale": float(scale),
        "frame_stride": int(frame_stride),
        "method": method,
        "config": _fingerprint(
            [
                asdict(bg_cfg),
                asdict(opts.masks),
                asdict(opts.association),
                opts.work_scale,
                None
                if volume is None
                else [volume.basis.tolist(), volume.lo.tolist(), volume.hi.tolist()],
                None if ext is None else ext.signature(),  # its files, by name and content
                [_camera_signature(rig[n]) for n in names],
                # the videos and the clean plates by name and content (a file replaced under
                # the same name, after an interrupted run, resumed the store and its labels)
                {n: file_identity(p) for n, p in sorted(videos.items())},
                {n: file_identity(p) for n, p in sorted(plates.items())},
                None if opts.persons is None else [asdict(opts.persons), opts.persons_hints],
                association,
                repr(opts.crowd) if association == "keypoints" else None,
            ]
            # the keypoint tracker's time step (given only: the stores of runs without keep
            # their keys)
            + ([float(opts.fps)] if opts.fps is not None else [])
        ),
        "association": association,
    }
    out_h5 = Path(out_h5)
    work = out_h5.with_name(out_h5.name + ".work")
    work_key = _fingerprint(
        [
            settings,
            {n: [str(p), os.path.getsize(p), os.path.getmtime(p)] for n, p in videos.items()},
            # the part stores hold crops of this size: another size found them and failed on
            # a hidden work file ("written with crop_size=64, asked to append crop_size=96")
            int(crop_size),
        ]
    )
    return ExtractPlan(
        videos, rig, out_h5, names, infos, n_frames, frames, sizes, work_sizes, crop_size,
        float(scale), frame_stride, bg_cfg, opts, ext, plates, truth_files, settings, work,
        association, work_key,
    )  # fmt: skip


def prepare_work(plan: ExtractPlan) -> None:
    """The work folder, reset when the inputs or settings changed since a previous, interrupted
    run. Called once the store has accepted the run's settings: a store that refuses them
    (another crop size, stride or association) must not cost the interrupted run's masks and
    association, which the same settings as before would resume."""
    marker = plan.work / "settings.json"
    if plan.work.exists() and (
        not marker.is_file() or json.loads(marker.read_text()).get("key") != plan.work_key
    ):
        shutil.rmtree(plan.work)
    plan.work.mkdir(parents=True, exist_ok=True)
    atomic_write_json(marker, {"key": plan.work_key, "settings": plan.settings})


def _mask_jobs(plan: ExtractPlan) -> list[MaskJob]:
    ext, opts = plan.external, plan.options
    return [
        MaskJob(
            n,
            str(plan.videos[n]),
            tuple(plan.frames),
            plan.n_frames,
            plan.sizes[n],
            plan.work_sizes[n],
            plan.background,
            opts.masks,
            str(plan.work / f"labels_{n}.h5"),
            external_masks=str(ext.mask_files[n])
            if ext is not None and n in ext.mask_files
            else None,
            external_boxes=ext.camera_boxes(n) if ext is not None else None,
            clean_plate=str(plan.plates[n]) if n in plan.plates else None,
            persons=opts.persons,
            persons_models_dir=opts.persons_models_dir,
            persons_hints=opts.persons_hints,
            instances=plan.association == "keypoints",
        )
        for n in plan.names
    ]


def keypoint_tracker_timing(crowd: CrowdConfig, frame_stride: int, fps: float):
    """The crowd settings and step_seconds for the keypoint id tracker on every
    `frame_stride`-th frame: it times raw frame numbers (1 / fps between consecutive ones) and
    counts its memory and its full-velocity step in processed frames (`TrackerConfig.
    frame_stride`). (stride / fps made every velocity `stride` times too slow and the speed gate
    that much looser.)"""
    if frame_stride > 1:
        crowd = replace(crowd, tracker=replace(crowd.tracker, frame_stride=frame_stride))
    return crowd, 1.0 / fps


def _associate(plan: ExtractPlan, active: list[str], progress) -> AssociationSummary:
    """Phase 2, resumed from the work folder's association.json when it is there."""
    marker = plan.work / "association.json"
    if marker.is_file():
        return AssociationSummary(**json.loads(marker.read_text()))
    if not active:
        return AssociationSummary.empty(plan.frames)
    if plan.association == "keypoints":
        crowd, step_seconds = keypoint_tracker_timing(
            plan.options.crowd, plan.frame_stride, plan.fps
        )
        summary = associate_scene_keypoints(
            {n: plan.work / f"labels_{n}.h5" for n in active},
            plan.rig.subset(active),  # with the rig's up (where people stand)
            {n: plan.videos[n] for n in active},
            plan.work_sizes,
            plan.frames,
            plan.work,
            crowd,
            plan.options.persons_models_dir,
            plan.options.association.min_track_frames,
            progress,
            step_seconds=step_seconds,
        )
        atomic_write_json(marker, asdict(summary))
        return summary
    ext = plan.external
    global_ids = bool(
        ext is not None and ext.global_ids and all(n in ext.mask_files for n in active)
    )
    summary = associate_scene(
        {n: plan.work / f"labels_{n}.h5" for n in active},
        [plan.rig[n] for n in active],
        plan.work_sizes,
        plan.frames,
        plan.work,
        plan.options.association,
        plan.options.volume,
        global_ids,
        progress,
        step_seconds=plan.frame_stride / plan.fps,
    )
    atomic_write_json(marker, asdict(summary))
    return summary


def _visible_views(plan: ExtractPlan) -> dict[str, tuple[tuple[int, int], ...]] | None:
    """Per camera, the (frame, person) truth views at least 30% visible (by joints), when the
    truth masks belong to a synthetic scene folder with `truth/views.parquet`."""
    masks_dir = next((p for p in plan.truth_files.values() if p is not None), None)
    if masks_dir is None:
        return None
    scene = next((d for d in Path(masks_dir).parents if has_scene_truth(d)), None)
    if scene is None:
        return None
    views = visible_truth_views(scene, plan.names)
    return {n: tuple(fp for fp in x if fp[0] in plan.frame_set) for n, x in views.items()}


def _crop_jobs(
    plan: ExtractPlan, active: list[str], done: set, summary: AssociationSummary
) -> list[CropJob]:
    jobs = []
    visible = _visible_views(plan)
    for n in active:
        ci = plan.names.index(n)
        truth = plan.truth_files.get(n)
        jobs.append(
            CropJob(
                plan.rig[n],
                ci,
                tuple(plan.names),
                str(plan.videos[n]),
                str(plan.work / f"persons_{n}.h5"),
                tuple(f for f in plan.frames if (f, ci) not in done),
                plan.work_sizes[n],
                plan.crop_size,
                plan.scale,
                str(plan.work / f"part_{n}.h5"),
                plan.settings,
                plan.options.commit_frames,
                str(truth) if truth else None,
                plan.options.association.min_mask_fraction,
                tuple(summary.short_tracks),
                visible.get(n) if visible is not None else None,
                compression=plan.options.compression,
                compression_level=plan.options.compression_level,
            )
        )
    return jobs


def _run_phases(plan: ExtractPlan, writer: CropStoreWriter, progress, executor_map) -> PhaseOutcome:
    """Phases 1-4 into `writer` for the (frame, camera) pairs not done yet."""
    names, frames = plan.names, plan.frames
    done = writer.done_pairs()
    resumed = sum(1 for f in frames for ci in range(len(names)) if (f, ci) in done)
    outcome = PhaseOutcome({n: CameraReport() for n in names}, resumed)
    if resumed == len(frames) * len(names):
        return outcome
    timings = outcome.timings

    t0 = time.perf_counter()
    for r in _map(
        executor_map, compute_camera_masks, _mask_jobs(plan), "foreground masks per camera"
    ):
        outcome.per_camera[r.camera].seconds_masks = r.seconds
        if r.frames_with_blobs == 0:
            outcome.skipped_cameras.append(r.camera)
    timings["masks"] = time.perf_counter() - t0
    active = [n for n in names if n not in outcome.skipped_cameras]

    t0 = time.perf_counter()
    outcome.summary = _associate(plan, active, progress)
    timings["association"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    crop_jobs = _crop_jobs(plan, active, done, outcome.summary)
    for r in _map(executor_map, extract_camera_crops, crop_jobs, "crops per camera"):
        outcome.per_camera[r.camera].seconds_crops = r.seconds
        outcome.truth_rows.extend(r.truth)
        outcome.truth_views += r.truth_views
        outcome.truth_missed += r.truth_views_missed
        outcome.visible_views += r.visible_views
        outcome.visible_missed += r.visible_views_missed
    timings["crops"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    for job in crop_jobs:
        merge_part(writer, Path(job.part), job.camera_index, plan.options.commit_frames)
    for n in outcome.skipped_cameras:  # cameras that saw no one: their frames are done, empty
        ci = names.index(n)
        pairs = [(f, ci) for f in frames if (f, ci) not in done]
        writer.commit(CropBatch.empty(plan.crop_size, plan.association == "keypoints"), pairs)
    timings["merge"] = time.perf_counter() - t0
    return outcome


def scores_by_source(rows: list[CropTruth]) -> dict[str, SourceScore]:
    """Truth scores of the crops grouped by where their views came from (`CropTruth.source`)."""
    out = {}
    for source in sorted({r.source for r in rows}):
        own = [r for r in rows if r.source == source]
        rest = [r for r in rows if r.source != source]
        acc, n = association_accuracy(rest)
        iou = float(np.mean([r.iou for r in own]))
        out[source] = SourceScore(len(own), iou, acc if n else None)
    return out


def ids_against_truth(rows: list[CropTruth]) -> dict[str, dict]:
    """Per extracted id, its first and last frame and how many of its crops show each truth
    person (0: nobody), e.g. {"11": {"frames": [15, 47], "truth": {"2": 180}}}: a person split
    into two ids, or a ghost, is plain to see."""
    frames: dict[int, list[int]] = {}
    truth: dict[int, Counter] = {}
    for r in rows:
        frames.setdefault(r.person_id, []).append(r.frame)
        truth.setdefault(r.person_id, Counter())[r.truth_id] += 1
    return {
        str(pid): {
            "frames": [min(frames[pid]), max(frames[pid])],
            "truth": {str(t): n for t, n in sorted(truth[pid].items())},
        }
        for pid in sorted(frames)
    }


def _report(plan: ExtractPlan, outcome: PhaseOutcome) -> ExtractReport:
    store = CropStore(plan.out_h5)
    cam_col = store.index.column("camera_index").to_numpy()
    frame_col = store.index.column("frame").to_numpy()
    per_cam, truth_rows, frames = outcome.per_camera, outcome.truth_rows, plan.frames
    for ci, n in enumerate(plan.names):
        sel = cam_col == ci
        per_cam[n].crops = int(sel.sum())
        per_cam[n].frames_with_people = int(len(np.unique(frame_col[sel])))
        per_cam[n].frames_without_people = len(frames) - per_cam[n].frames_with_people
        rows = [r for r in truth_rows if r.camera == n]
        if rows:
            per_cam[n].mask_iou = float(np.mean([r.iou for r in rows]))
    summary = outcome.summary
    if summary is not None:
        with_people = summary.frames_with_people()
    else:  # everything was already done: count from the store
        with_people = int(len(np.unique(frame_col)))
    acc, n_scored = association_accuracy(truth_rows)
    single = store.index.column("single_view").to_numpy() if len(store) else np.zeros(0, bool)
    return ExtractReport(
        store=str(plan.out_h5),
        cameras=plan.names,
        frames_total=plan.n_frames,
        frame_stride=plan.frame_stride,
        frames_considered=len(frames),
        frames_with_people=with_people,
        frames_skipped_empty=len(frames) - with_people,
        cameras_skipped=outcome.skipped_cameras,
        per_camera=per_cam,
        crops=len(store),
        persons=int(len(np.unique(store.index.column("person_id").to_numpy()))),
        multiview_groups=len(store.multiview_groups(2)),
        pairs_resumed=outcome.pairs_resumed,
        short_tracks_dropped=list(summary.short_tracks) if summary else [],
        mask_iou=float(np.mean([r.iou for r in truth_rows])) if truth_rows else None,
        association_accuracy=acc if n_scored else None,
        crops_scored=n_scored,
        truth_views=outcome.truth_views,
        truth_views_missed=outcome.truth_missed,
        visible_views=outcome.visible_views,
        visible_views_missed=outcome.visible_missed,
        timings=outcome.timings,
        settings={
            **plan.settings,
            "crop_size": plan.crop_size,
            "work_sizes": plan.work_sizes,
            "voxels": summary.voxels if summary else None,
        },
        association_method=plan.association,
        single_view_crops=int(np.count_nonzero(single)),
        truth_by_source=scores_by_source(truth_rows),
        truth_by_id=ids_against_truth(truth_rows),
    )


def extract_scene(
    videos: dict[str, Path],
    rig: Rig,
    out_h5: Path,
    *,
    crop_size: int = 256,
    scale: float = 1.2,
    frame_stride: int = 1,
    method: str = "median",
    external: Path | str | ExternalDetections | None = None,
    truth: Path | str | None = None,
    progress: Callable | None = None,
    executor_map: Callable | None = None,
    options: ExtractOptions | None = None,
) -> ExtractReport:
    """Person crops, masks and intrinsics from every camera of a scene into one crop store.

    videos: camera name -> video file (synchronised, equal length; names must be rig cameras).
    external: folder of external masks/boxes (docs/formats/external_masks.md); they take
      precedence over the background model for the cameras they cover.
    truth: `<scene>/truth` (or its `masks/` folder) with id masks, for IoU and association scores.
    progress: optional `progress(iterable, description=..., total=...)` wrapper (a progress bar).
    executor_map: optional `map(fn, items, description)` for per-camera work (e.g. a process pool).
    A run that stops half-way leaves the store marked incomplete; rerunning resumes it.
    """
    t_start = time.perf_counter()
    plan = plan_extraction(
        videos, rig, out_h5, crop_size=crop_size, scale=scale, frame_stride=frame_stride,
        method=method, external=external, truth=truth, options=options or ExtractOptions(),
    )  # fmt: skip
    with CropStoreWriter(
        plan.out_h5,
        plan.names,
        crop_size,
        plan.settings,
        plan.options.compression,
        plan.options.compression_level,
        landmarks=plan.association == "keypoints",
    ) as writer:
        prepare_work(plan)
        outcome = _run_phases(plan, writer, progress, executor_map)
        writer.finalize(
            {
                # file names only: a workspace copied elsewhere keeps identical bytes
                "source_videos": json.dumps({n: p.name for n, p in plan.videos.items()}),
                "n_frames": plan.n_frames,
            }
        )
    report = _report(plan, outcome)
    if not plan.options.keep_work and plan.work.exists():
        shutil.rmtree(plan.work)
    report.timings["total"] = time.perf_counter() - t_start
    return report
