"""The whole extraction of one scene: videos + rig -> crop store + report.

Four phases, resumable through a work folder next to the store (`<store>.work/`):

1. masks (per camera, parallel): learn the background, label foreground blobs per frame at a
   reduced "work" resolution, or take external masks/boxes instead.
2. association (all cameras, sequential in time): visual hull -> people -> ids over time ->
   per-camera person label images.
3. crops (per camera, parallel): undistorted square crops of image and mask with their own
   intrinsics, into a per-camera part store; scored against truth masks when given.
4. merge: the part stores are appended to the scene store frame by frame, then the Parquet
   index is written and the store marked complete.

Per-camera work lives in module-level functions taking one picklable job, so `executor_map`
can be a process pool's `map`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import h5py
import numpy as np

from calibration import Camera, Rig
from gst.data.associate import (
    AssociationConfig,
    CaptureVolume,
    PersonTracker,
    VoxelGrid,
    link_tracklets,
)
from gst.data.background import BackgroundConfig, build_background, sample_indices
from gst.data.crop import (
    crop_intrinsics,
    crop_maps,
    hmr_crop_box,
    mask_outline_full_res,
    resample,
    undistorted_box,
)
from gst.data.evaluate import CropTruth, association_accuracy
from gst.data.external import (
    ExternalDetections,
    IdMaskFile,
    boxes_to_labels,
    find_mask_file,
    read_external,
    resize_labels,
)
from gst.data.masks import MaskConfig, clean_mask
from gst.data.store import CropBatch, CropStore, CropStoreWriter
from gst.data.video import VideoError, check_videos, probe_video, read_frames, scaled_size
from gst.detect.blazepose import BlazePose
from gst.detect.persons import PersonSegmenter, SegmenterConfig
from gst.detect.weights import model_paths

WORK_MAX_SIDE = 960  # default work resolution: longer image side in pixels


class ExtractError(ValueError):
    """The extraction cannot proceed; the message names the camera, file or setting."""


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
class ExtractReport:
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
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


# -- per-camera phase 1: foreground labels ----------------------------------------------------


@dataclass(frozen=True, eq=False)
class MaskJob:
    camera: str
    video: str
    frames: tuple[int, ...]
    n_frames: int
    full_size: tuple[int, int]
    work_size: tuple[int, int]
    background: BackgroundConfig
    masks: MaskConfig
    out: str
    external_masks: str | None = None
    clean_plate: str | None = None  # video of the empty scene to learn the background from
    external_boxes: dict | None = None  # frame -> [(person_id, box)] in full-resolution pixels
    cache_bytes: int = 1 << 30  # decode once and keep work frames in memory up to this size
    persons: SegmenterConfig | None = None  # learned person masks instead of the background model
    persons_models_dir: str | None = None
    persons_hints: bool = True


@dataclass(frozen=True)
class MaskJobResult:
    camera: str
    frames_with_blobs: int
    blobs: int
    seconds: float
    cached: bool


def _write_atomic_h5(path: Path, fill: Callable[[h5py.File], None]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as f:
        fill(f)
    os.replace(tmp, path)


def compute_camera_masks(job: MaskJob) -> MaskJobResult:
    """Foreground label images of one camera (uint8 at work resolution) into `job.out`."""
    out = Path(job.out)
    if out.is_file():
        with h5py.File(out, "r") as f:
            return MaskJobResult(
                job.camera,
                int(f.attrs["frames_with_blobs"]),
                int(f.attrs["blobs"]),
                float(f.attrs["seconds"]),
                True,
            )
    t0 = time.perf_counter()
    w, h = job.work_size
    sx = w / job.full_size[0]
    labels = np.zeros((len(job.frames), h, w), dtype=np.uint8)
    pos = {f: i for i, f in enumerate(job.frames)}
    if job.external_masks:
        ext = IdMaskFile(job.external_masks, job.camera)
        for f in job.frames:
            m = ext.get(f)
            if m is not None:
                labels[pos[f]] = resize_labels(m, (w, h))
        ext.close()
    else:
        cache: dict[int, np.ndarray] = {}
        if job.clean_plate:
            # An empty-scene clip of this camera: learn the background from it alone.
            plate = probe_video(job.clean_plate, job.camera)
            if (plate.width, plate.height) != tuple(job.full_size):
                raise VideoError(
                    f"camera '{job.camera}' background video {job.clean_plate}: frames are "
                    f"{plate.width}x{plate.height}, the camera's video is "
                    f"{job.full_size[0]}x{job.full_size[1]}"
                )
            idx = sample_indices(plate.frames, job.background.samples)
            samples = np.stack(
                [img for _, img in read_frames(job.clean_plate, idx, job.camera, sx)]
            )
        elif (
            len(set(sample_indices(job.n_frames, job.background.samples)) | set(job.frames))
            * w
            * h
            * 3
            <= job.cache_bytes
        ):
            # Short clip: decode once, keep the small work frames for the second pass.
            idx = sample_indices(job.n_frames, job.background.samples)
            cache = dict(read_frames(job.video, sorted(set(idx) | set(job.frames)), job.camera, sx))
            samples = np.stack([cache[i] for i in idx])
        else:
            idx = sample_indices(job.n_frames, job.background.samples)
            samples = np.stack([img for _, img in read_frames(job.video, idx, job.camera, sx)])
        model = build_background(samples, job.background)
        del samples
        segmenter = None
        if job.persons is not None:
            segmenter = PersonSegmenter(BlazePose(job.persons_models_dir), job.persons)
        frames_iter = (
            ((f, cache.pop(f)) for f in job.frames)
            if cache
            else read_frames(job.video, job.frames, job.camera, sx)
        )
        for f, img in frames_iter:
            lab, blobs = clean_mask(model.foreground(img), job.masks)
            if segmenter is not None:
                lab, _ = segmenter.segment(img, [b.box for b in blobs] if job.persons_hints else ())
            if job.external_boxes is not None:
                lab = boxes_to_labels(
                    lab, job.external_boxes.get(f, []), (w, h), (sx, h / job.full_size[1])
                )
            labels[pos[f]] = lab
    per_frame_max = labels.reshape(len(labels), -1).max(axis=1)  # clean_mask labels are 1..n
    n_with = int(np.count_nonzero(per_frame_max))
    n_blobs = int(per_frame_max.astype(np.int64).sum()) if not job.external_masks else -1
    seconds = time.perf_counter() - t0

    def fill(f: h5py.File) -> None:
        f.create_dataset(
            "labels", data=labels, chunks=(1, h, w), compression="gzip", compression_opts=1
        )
        f.create_dataset("frames", data=np.asarray(job.frames, dtype=np.int64))
        f.attrs.update(
            {
                "frames_with_blobs": n_with,
                "blobs": n_blobs,
                "seconds": seconds,
                "camera": job.camera,
            }
        )

    _write_atomic_h5(out, fill)
    return MaskJobResult(job.camera, n_with, n_blobs, seconds, False)


# -- phase 2: association --------------------------------------------------------------------


def _values_present(labels: np.ndarray) -> np.ndarray:
    """Distinct values of a uint8 label image (a histogram: much faster than np.unique)."""
    return np.nonzero(np.bincount(labels.reshape(-1), minlength=256))[0]


def associate_scene(
    label_files: dict[str, Path],
    cameras: list[Camera],
    work_sizes: dict[str, tuple[int, int]],
    frames: list[int],
    out_dir: Path,
    config: AssociationConfig,
    volume: CaptureVolume | None,
    global_ids: bool = False,
    progress: Callable | None = None,
    step_seconds: float = 1 / 30,
) -> dict:
    """Per-frame people and per-camera person labels, written to `out_dir/persons_<cam>.h5`.

    Returns a summary (people per frame, ids). With `global_ids` the label values already are
    person ids consistent across cameras (external masks that say so) and are used as they are.
    """
    names = [c.name for c in cameras]
    if len(names) < 2 and not global_ids:
        raise ExtractError(
            f"only camera(s) {names} see anyone; associating people across views "
            "needs at least two cameras that see them"
        )
    grid = None
    if not global_ids:
        grid = VoxelGrid(
            cameras, work_sizes, volume or CaptureVolume.from_rig(Rig(tuple(cameras))), config
        )
        if len(grid) == 0:
            raise ExtractError(
                f"no voxel of the capture volume is seen by {config.min_views} of the cameras "
                f"{names}; check the calibration or give the volume explicitly"
            )
    tracker = PersonTracker(
        config.track_max_speed, step_seconds, config.track_slack, config.track_max_gap
    )
    inputs = {n: h5py.File(label_files[n], "r") for n in names}
    tmp_files = {}
    outs = {}
    slots: dict[str, list[tuple[int, int, int]]] = {n: [] for n in names}
    views: dict[str, list[tuple[float, ...]]] = {n: [] for n in names}  # box x0 y0 x1 y1, support
    per_frame: list[list[int]] = []
    observed: dict[int, list[tuple[int, np.ndarray]]] = {}  # id -> (frame position, ground)
    try:
        for n in names:
            w, h = work_sizes[n]
            tmp_files[n] = out_dir / f"persons_{n}.h5.tmp"
            outs[n] = h5py.File(tmp_files[n], "w")
            outs[n].create_dataset(
                "labels",
                shape=(len(frames), h, w),
                dtype="uint8",
                chunks=(1, h, w),
                compression="gzip",
                compression_opts=1,
            )
            outs[n].create_dataset("frames", data=np.asarray(frames, dtype=np.int64))
        it: Iterable = enumerate(frames)
        if progress is not None:
            it = progress(it, description="associating people across cameras", total=len(frames))
        for i, frame in it:
            labels = {n: inputs[n]["labels"][i] for n in names}
            if global_ids:
                ids = sorted({int(v) for n in names for v in np.unique(labels[n]) if v > 0})
                per_frame.append(ids)
                for n in names:
                    outs[n]["labels"][i] = labels[n]
                    for v in _values_present(labels[n]):
                        if v > 0:
                            slots[n].append((frame, int(v), int(v)))
                            views[n].append((np.nan, np.nan, np.nan, np.nan, np.nan))
                continue
            assoc = grid.associate(labels)
            ids = tracker.update(assoc.persons)
            per_frame.append(ids)
            for pid, person in zip(ids, assoc.persons, strict=True):
                observed.setdefault(pid, []).append((i, person.ground.copy()))
            for n in names:
                lab = assoc.labels[n]
                outs[n]["labels"][i] = lab
                for v in _values_present(lab):
                    view = assoc.views[n][int(v) - 1] if v > 0 else None
                    if view is not None:
                        slots[n].append((frame, int(v), ids[int(v) - 1]))
                        views[n].append((*view[0].tolist(), view[1]))
        if not global_ids and observed:
            # Offline: join id fragments of one person (lost for a while, then found again).
            link = link_tracklets(
                observed, step_seconds, config.link_speed, config.link_slack, config.link_max_gap
            )
            per_frame = [[link[i] for i in ids] for ids in per_frame]
            for n in names:
                slots[n] = [(f, v, link.get(pid, pid)) for f, v, pid in slots[n]]
        for n in names:
            outs[n].create_dataset(
                "slots", data=np.asarray(slots[n], dtype=np.int64).reshape(-1, 3)
            )
            outs[n].create_dataset(
                "views", data=np.asarray(views[n], dtype=np.float64).reshape(-1, 5)
            )
            outs[n].close()
            os.replace(tmp_files[n], out_dir / f"persons_{n}.h5")
    finally:
        for f in inputs.values():
            f.close()
        for n, f in outs.items():
            if f.id.valid:
                f.close()
            if tmp_files[n].exists():
                tmp_files[n].unlink()
    counts: dict[int, int] = {}
    for ids in per_frame:
        for i in ids:
            counts[i] = counts.get(i, 0) + 1
    short = sorted(i for i, c in counts.items() if c < config.min_track_frames and not global_ids)
    return {
        "frames": frames,
        "ids": per_frame,
        "voxels": len(grid) if grid is not None else 0,
        "short_tracks": short,
    }


# -- per-camera phase 3: crops ----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CropJob:
    camera: Camera
    camera_index: int
    camera_names: tuple[str, ...]
    video: str
    persons_file: str
    frames: tuple[int, ...]  # frames still to do for this camera
    work_size: tuple[int, int]
    crop_size: int
    scale: float
    part: str
    settings: dict
    commit_frames: int = 16
    truth_masks: str | None = None
    min_truth_fraction: float = 0.0003
    drop_ids: tuple[int, ...] = ()  # person ids not to crop (tracks too short to trust)


@dataclass
class CropJobResult:
    camera: str
    crops: int
    frames_with_people: int
    frames_without_people: int
    seconds: float
    truth: list[CropTruth] = field(default_factory=list)
    truth_views: int = 0
    truth_views_missed: int = 0


def crop_person(
    frame: np.ndarray,
    person_mask: np.ndarray,
    camera: Camera,
    crop_size: int,
    scale: float,
    extra_box: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Crop one person: (image S x S x 3, mask S x S coverage 0..255, K_crop, person box, crop box).

    `person_mask` is boolean at work resolution (any size that is a scaling of the frame).
    `extra_box` (x0, y0, x1, y1 pixel edges at work resolution) is a region the person box must
    also cover (where the 3D hull says the person is). Returns None for an empty mask.
    """
    h, w = frame.shape[:2]
    src_scale = (person_mask.shape[1] / w, person_mask.shape[0] / h)
    pts, half = mask_outline_full_res(person_mask, src_scale)
    if len(pts) == 0:
        return None
    if extra_box is not None and np.all(np.isfinite(extra_box)):
        # Box edges to full-resolution pixel centres along its outline (the lens bends it).
        ex0, ey0, ex1, ey1 = extra_box
        t = np.linspace(0.0, 1.0, 9)
        xs = ex0 + (ex1 - ex0) * t
        ys = ey0 + (ey1 - ey0) * t
        outline = np.concatenate(
            [
                np.stack([xs, np.full_like(xs, ey0)], 1),
                np.stack([xs, np.full_like(xs, ey1)], 1),
                np.stack([np.full_like(ys, ex0), ys], 1),
                np.stack([np.full_like(ys, ex1), ys], 1),
            ]
        )
        outline = outline / np.array(src_scale) - 0.5
        pts = np.concatenate([pts, outline])
    box = undistorted_box(camera, pts, half)
    cbox = hmr_crop_box(box, scale)
    mapx, mapy = crop_maps(camera, cbox, crop_size)
    shrink = cbox.side / crop_size
    image = resample(frame, mapx, mapy, shrink)
    sx, sy = src_scale
    mmx = (mapx + 0.5) * np.float32(sx) - 0.5
    mmy = (mapy + 0.5) * np.float32(sy) - 0.5
    mask = resample(person_mask.astype(np.float32), mmx, mmy, shrink * min(sx, sy))
    mask = np.clip(mask * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return image, mask, crop_intrinsics(camera.K, cbox, crop_size), box, cbox.as_array()


def score_against_truth(
    work_mask: np.ndarray, truth: np.ndarray, truth_areas: np.ndarray
) -> tuple[int, float]:
    """(truth id, IoU) of a work-resolution person mask against a full-resolution truth id mask.

    The mask is upsampled bilinearly (threshold 0.5, as `cv2.resize` would) only over its own
    bounding box; `truth_areas[k]` is the pixel count of truth id k in the whole image.
    """
    H, W = truth.shape
    h, w = work_mask.shape
    sx, sy = w / W, h / H
    rows = np.nonzero(work_mask.any(axis=1))[0]
    cols = np.nonzero(work_mask.any(axis=0))[0]
    if len(rows) == 0:
        return 0, 0.0
    x0 = max(0, int(np.floor((cols[0] - 1) / sx)))
    x1 = min(W, int(np.ceil((cols[-1] + 2) / sx)))
    y0 = max(0, int(np.floor((rows[0] - 1) / sy)))
    y1 = min(H, int(np.ceil((rows[-1] + 2) / sy)))
    mx = ((np.arange(x0, x1, dtype=np.float32) + 0.5) * sx - 0.5)[None].repeat(y1 - y0, 0)
    my = ((np.arange(y0, y1, dtype=np.float32) + 0.5) * sy - 0.5)[:, None].repeat(x1 - x0, 1)
    up = (
        cv2.remap(
            work_mask.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        >= 0.5
    )
    roi = truth[y0:y1, x0:x1]
    ids = roi[up]
    ids = ids[ids > 0]
    if len(ids) == 0:
        return 0, 0.0
    tid = int(np.bincount(ids).argmax())
    inter = int(np.count_nonzero(ids == tid))
    union = int(np.count_nonzero(up)) + int(truth_areas[tid]) - inter
    return tid, inter / union if union else 0.0


def extract_camera_crops(job: CropJob) -> CropJobResult:
    """Crops of every assigned person in one camera, appended to the part store `job.part`."""
    t0 = time.perf_counter()
    cam = job.camera
    with h5py.File(job.persons_file, "r") as pf:
        p_frames = pf["frames"][()]
        row_of = {int(f): i for i, f in enumerate(p_frames)}
        slot_rows = pf["slots"][()]
        view_rows = pf["views"][()]
        by_frame: dict[int, list[tuple[int, int, np.ndarray, float]]] = {}
        drop = set(job.drop_ids)
        for (f, slot, pid), view in zip(slot_rows, view_rows, strict=True):
            if pid in drop:
                continue
            by_frame.setdefault(int(f), []).append((int(slot), int(pid), view[:4], float(view[4])))
        result = CropJobResult(cam.name, 0, 0, 0, 0.0)
        truth = IdMaskFile(job.truth_masks, cam.name) if job.truth_masks else None
        # The part store is temporary: no compression (the scene store compresses once).
        with CropStoreWriter(
            job.part, list(job.camera_names), job.crop_size, job.settings, compression="none"
        ) as part:
            done = {f for f, c in part.done_pairs() if c == job.camera_index}
            todo = [f for f in job.frames if f not in done]
            with_people = [f for f in todo if f in by_frame]
            pending: list[CropBatch] = []
            pending_done: list[tuple[int, int]] = []

            def flush() -> None:
                batch = CropBatch.concat(pending) if pending else CropBatch.empty(job.crop_size)
                part.commit(batch, pending_done)
                pending.clear()
                pending_done.clear()

            frames_iter = iter(read_frames(job.video, with_people, cam.name))
            next_frame = next(frames_iter, None)
            for f in todo:
                rows = []
                scored: list[CropTruth] = []
                gt = truth.get(f) if truth is not None else None
                gt_areas = np.bincount(gt.reshape(-1), minlength=256) if gt is not None else None
                if f in by_frame:
                    fi, image = next_frame
                    assert fi == f
                    next_frame = next(frames_iter, None)
                    labels = pf["labels"][row_of[f]]
                    for slot, pid, extra_box, support in by_frame[f]:
                        pmask = labels == slot
                        got = crop_person(image, pmask, cam, job.crop_size, job.scale, extra_box)
                        if got is None:
                            continue
                        img, msk, Kc, box, cbox = got
                        rows.append(
                            CropBatch(
                                img[None],
                                msk[None],
                                Kc[None],
                                cam.R[None],
                                cam.t[None],
                                box[None],
                                cbox[None],
                                np.array([job.camera_index], np.int32),
                                np.array([f], np.int64),
                                np.array([pid], np.int64),
                                np.array([support], np.float32),
                            )
                        )
                        if gt is not None:
                            tid, iou = score_against_truth(pmask, gt, gt_areas)
                            scored.append(CropTruth(f, cam.name, pid, tid, iou))
                if gt is not None:
                    big = set(
                        np.nonzero(gt_areas >= job.min_truth_fraction * gt.size)[0].tolist()
                    ) - {0}
                    result.truth_views += len(big)
                    result.truth_views_missed += len(big - {r.truth_id for r in scored})
                    result.truth.extend(scored)
                if rows:
                    result.frames_with_people += 1
                    result.crops += len(rows)
                    pending.extend(rows)
                else:
                    result.frames_without_people += 1
                pending_done.append((f, job.camera_index))
                if len(pending_done) >= job.commit_frames:
                    flush()
            flush()
        if truth is not None:
            truth.close()
    result.seconds = time.perf_counter() - t0
    return result


# -- phase 4: merge ---------------------------------------------------------------------------


def merge_part(
    writer: CropStoreWriter, part_path: Path, camera_index: int, commit_frames: int
) -> int:
    """Append a camera's part store to the scene store, frame chunk by frame chunk; returns the
    number of (frame, camera) pairs added."""
    done_main = writer.done_pairs()
    added = 0
    with h5py.File(part_path, "r") as f:
        n = int(f.attrs["n_committed"])
        n_done = int(f.attrs["n_done"])
        frames_col = f["frame"][:n]
        part_done = sorted(int(fr) for fr, c in f["done"][:n_done] if c == camera_index)
        todo = [fr for fr in part_done if (fr, camera_index) not in done_main]
        for i0 in range(0, len(todo), commit_frames):
            chunk = todo[i0 : i0 + commit_frames]
            rows = np.nonzero(np.isin(frames_col, chunk))[0]
            if len(rows):
                a, b = int(rows.min()), int(rows.max()) + 1
                if b - a != len(rows):
                    raise ExtractError(
                        f"{part_path}: rows of frames {chunk[0]}..{chunk[-1]} are not contiguous"
                    )
                batch = CropBatch(**{k: f[k][a:b] for k in CropBatch.__dataclass_fields__})
            else:
                batch = CropBatch.empty(writer.crop_size)
            writer.commit(batch, [(fr, camera_index) for fr in chunk])
            added += len(chunk)
    return added


# -- the whole job ----------------------------------------------------------------------------


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


def _map(executor_map, fn, items, description):
    if executor_map is None:
        return [fn(x) for x in items]
    return list(executor_map(fn, items, description))


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
    opts = options or ExtractOptions()
    out_h5 = Path(out_h5)
    if crop_size < 16:
        raise ExtractError(f"crop_size must be >= 16 pixels, got {crop_size}")
    if scale < 1.0:
        raise ExtractError(f"scale must be >= 1 (the crop surrounds the person box), got {scale}")
    if frame_stride < 1:
        raise ExtractError(f"frame_stride must be >= 1, got {frame_stride}")
    bg_cfg = BackgroundConfig(**{**asdict(opts.background), "method": method})
    videos = {str(k): Path(v) for k, v in videos.items()}
    infos = check_videos(videos, rig.names, {c.name: (c.width, c.height) for c in rig})
    names = [n for n in rig.names if n in videos]  # rig order
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
        info = probe_video(p, n)
        if (info.width, info.height) != sizes[n]:
            raise VideoError(
                f"camera '{n}' background video {p}: frames are {info.width}x{info.height}, "
                f"the camera's video is {sizes[n][0]}x{sizes[n][1]}"
            )
    if opts.persons is not None:
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
                if opts.volume is None
                else [opts.volume.basis.tolist(), opts.volume.lo.tolist(), opts.volume.hi.tolist()],
                str(getattr(ext, "root", None)),
                [_camera_signature(rig[n]) for n in names],
                {n: str(p) for n, p in sorted(plates.items())},
                None if opts.persons is None else [asdict(opts.persons), opts.persons_hints],
            ]
        ),
    }
    work = out_h5.with_name(out_h5.name + ".work")
    work_key = _fingerprint(
        [
            settings,
            {n: [str(p), os.path.getsize(p), os.path.getmtime(p)] for n, p in videos.items()},
        ]
    )
    marker = work / "settings.json"
    if work.exists() and (
        not marker.is_file() or json.loads(marker.read_text()).get("key") != work_key
    ):
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"key": work_key, "settings": settings}))
    timings: dict[str, float] = {}

    with CropStoreWriter(
        out_h5, names, crop_size, settings, opts.compression, opts.compression_level
    ) as writer:
        done_main = writer.done_pairs()
        pairs_resumed = sum(1 for f in frames for ci in range(len(names)) if (f, ci) in done_main)
        all_done = pairs_resumed == len(frames) * len(names)
        per_cam = {n: CameraReport() for n in names}
        skipped_cams: list[str] = []
        truth_rows: list[CropTruth] = []
        truth_views = truth_missed = 0
        summary = None
        if not all_done:
            # Phase 1: foreground labels per camera.
            t0 = time.perf_counter()
            jobs = []
            for n in names:
                boxes = ext.camera_boxes(n) if ext is not None else None
                jobs.append(
                    MaskJob(
                        n,
                        str(videos[n]),
                        tuple(frames),
                        n_frames,
                        sizes[n],
                        work_sizes[n],
                        bg_cfg,
                        opts.masks,
                        str(work / f"labels_{n}.h5"),
                        external_masks=str(ext.mask_files[n])
                        if ext is not None and n in ext.mask_files
                        else None,
                        external_boxes=boxes,
                        clean_plate=str(plates[n]) if n in plates else None,
                        persons=opts.persons,
                        persons_models_dir=opts.persons_models_dir,
                        persons_hints=opts.persons_hints,
                    )
                )
            for r in _map(executor_map, compute_camera_masks, jobs, "foreground masks per camera"):
                per_cam[r.camera].seconds_masks = r.seconds
                if r.frames_with_blobs == 0:
                    skipped_cams.append(r.camera)
            timings["masks"] = time.perf_counter() - t0
            active = [n for n in names if n not in skipped_cams]

            # Phase 2: association.
            t0 = time.perf_counter()
            assoc_marker = work / "association.json"
            global_ids = bool(
                ext is not None and ext.global_ids and all(n in ext.mask_files for n in active)
            )
            if assoc_marker.is_file():
                summary = json.loads(assoc_marker.read_text())
            elif active:
                fps = (
                    infos[names[0]].fps if infos[names[0]].fps > 0 else 30.0
                )  # unknown rate: assume 30
                summary = associate_scene(
                    {n: work / f"labels_{n}.h5" for n in active},
                    [rig[n] for n in active],
                    work_sizes,
                    frames,
                    work,
                    opts.association,
                    opts.volume,
                    global_ids,
                    progress,
                    step_seconds=frame_stride / fps,
                )
                assoc_marker.write_text(json.dumps({**summary, "active": active}))
            else:
                summary = {
                    "frames": frames,
                    "ids": [[] for _ in frames],
                    "voxels": 0,
                    "active": [],
                    "short_tracks": [],
                }
            timings["association"] = time.perf_counter() - t0

            # Phase 3: crops per camera.
            t0 = time.perf_counter()
            crop_jobs = []
            for n in active:
                ci = names.index(n)
                todo = tuple(f for f in frames if (f, ci) not in done_main)
                crop_jobs.append(
                    CropJob(
                        rig[n],
                        ci,
                        tuple(names),
                        str(videos[n]),
                        str(work / f"persons_{n}.h5"),
                        todo,
                        work_sizes[n],
                        crop_size,
                        float(scale),
                        str(work / f"part_{n}.h5"),
                        settings,
                        opts.commit_frames,
                        str(truth_files[n]) if truth_files.get(n) else None,
                        opts.association.min_mask_fraction,
                        tuple(summary["short_tracks"]),
                    )
                )
            for r in _map(executor_map, extract_camera_crops, crop_jobs, "crops per camera"):
                per_cam[r.camera].seconds_crops = r.seconds
                truth_rows.extend(r.truth)
                truth_views += r.truth_views
                truth_missed += r.truth_views_missed
            timings["crops"] = time.perf_counter() - t0

            # Phase 4: merge into the scene store.
            t0 = time.perf_counter()
            for job in crop_jobs:
                merge_part(writer, Path(job.part), job.camera_index, opts.commit_frames)
            # Cameras that saw no one: their frames are done (with no crops).
            for n in skipped_cams:
                ci = names.index(n)
                writer.commit(
                    CropBatch.empty(crop_size),
                    [(f, ci) for f in frames if (f, ci) not in done_main],
                )
            timings["merge"] = time.perf_counter() - t0
        writer.finalize(
            {
                "source_videos": json.dumps({n: str(p) for n, p in videos.items()}),
                "n_frames": n_frames,
            }
        )

    store = CropStore(out_h5)
    cam_col = store.index.column("camera_index").to_numpy()
    frame_col = store.index.column("frame").to_numpy()
    for ci, n in enumerate(names):
        sel = cam_col == ci
        per_cam[n].crops = int(sel.sum())
        per_cam[n].frames_with_people = int(len(np.unique(frame_col[sel])))
        per_cam[n].frames_without_people = len(frames) - per_cam[n].frames_with_people
        rows = [r for r in truth_rows if r.camera == n]
        if rows:
            per_cam[n].mask_iou = float(np.mean([r.iou for r in rows]))
    if summary is not None:
        short = set(summary["short_tracks"])
        with_people = sum(1 for ids in summary["ids"] if set(ids) - short)
    else:  # everything was already done: count from the store
        with_people = int(len(np.unique(frame_col)))
    acc, n_scored = association_accuracy(truth_rows)
    if not opts.keep_work and work.exists():
        shutil.rmtree(work)
    timings["total"] = time.perf_counter() - t_start
    return ExtractReport(
        store=str(out_h5),
        cameras=names,
        frames_total=n_frames,
        frame_stride=frame_stride,
        frames_considered=len(frames),
        frames_with_people=with_people,
        frames_skipped_empty=len(frames) - with_people,
        cameras_skipped=skipped_cams,
        per_camera=per_cam,
        crops=len(store),
        persons=int(len(np.unique(store.index.column("person_id").to_numpy()))),
        multiview_groups=len(store.multiview_groups(2)),
        pairs_resumed=pairs_resumed,
        short_tracks_dropped=list(summary["short_tracks"]) if summary else [],
        mask_iou=float(np.mean([r.iou for r in truth_rows])) if truth_rows else None,
        association_accuracy=acc if n_scored else None,
        crops_scored=n_scored,
        truth_views=truth_views,
        truth_views_missed=truth_missed,
        timings=timings,
        settings={
            **settings,
            "crop_size": crop_size,
            "work_sizes": work_sizes,
            "voxels": summary.get("voxels") if summary else None,
        },
    )


__all__ = [
    "ExtractError",
    "ExtractOptions",
    "ExtractReport",
    "CameraReport",
    "extract_scene",
    "compute_camera_masks",
    "extract_camera_crops",
    "crop_person",
    "VideoError",
]
