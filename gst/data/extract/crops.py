"""Extraction phase 3, per camera: undistorted square crops of image and mask with their own
intrinsics, into a per-camera part store; scored against truth masks when given.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import h5py
import numpy as np

from calibration import Camera
from calibration.camera import FIELD_MARGIN
from gst.data.crop import (
    crop_intrinsics,
    crop_maps,
    folded_pixels,
    hmr_crop_box,
    mask_outline_full_res,
    resample,
    undistorted_box,
)
from gst.data.evaluate import CropTruth
from gst.data.external import (
    IdMaskFile,
)
from gst.data.store import CropBatch, CropStoreWriter
from gst.video import read_frames


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
    # Synthetic truth: (frame, person) views of this camera where the person is at least
    # `MIN_VISIBLE_JOINTS` visible (their joints); the ones no crop covers are counted missed.
    visible_views: tuple[tuple[int, int], ...] | None = None
    # The part store's compression: the scene store's, so that merging it copies the compressed
    # crops as they are (gst.data.store.CropStoreWriter.commit_rows) and the compressing is
    # done here, one process per camera, instead of in the merging process.
    compression: str = "gzip"
    compression_level: int = 1


MIN_VISIBLE_JOINTS = 0.3  # share of a person's joints visible for a truth view to count


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
    visible_views: int = 0
    visible_views_missed: int = 0


def seen_truth_views(views) -> np.ndarray:
    """(M,) bool over a synthetic scene's truth views (`synth.truth.TruthViews`): at least
    `MIN_VISIBLE_JOINTS` of the person's joints visible, a view a person mask is expected in."""
    return views.visible.mean(axis=1) >= MIN_VISIBLE_JOINTS


def visible_truth_views(scene_dir, cameras) -> dict[str, list[tuple[int, int]]]:
    """Per camera of `cameras`, the (frame, person) views of a synthetic scene's truth
    (`truth/views.parquet`) in which at least `MIN_VISIBLE_JOINTS` of the person's joints are
    visible: the views a person mask is expected in."""
    # here, not at the top: the extraction's worker processes import this module, and synth
    # brings torch (tests/test_lazy_packages.py)
    from synth.truth import read_truth_views

    v = read_truth_views(scene_dir)
    keep = seen_truth_views(v)
    out: dict[str, list[tuple[int, int]]] = {str(n): [] for n in cameras}
    for f, p, c in zip(v.frame[keep], v.person_id[keep], v.camera[keep], strict=True):
        if c in out:
            out[c].append((int(f), int(p)))
    return out


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
        # Box edges to full-resolution pixel centres along its outline (the lens bends it),
        # within the field the lens model holds (landmarks far outside it are no evidence).
        mh, mw = person_mask.shape
        lo = -FIELD_MARGIN * np.array([mw, mh, mw, mh])
        ex0, ey0, ex1, ey1 = np.clip(extra_box, lo, np.array([mw, mh, mw, mh]) - lo)
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
    # Rays beyond the lens model's fold see nothing (the polynomial maps them back inside).
    folded = folded_pixels(mapx, mapy)
    if folded.any():
        image[folded] = 0
        mask[folded] = 0
    return image, mask, crop_intrinsics(camera.K, cbox, crop_size), box, cbox.as_array()


def landmarks_to_crop(camera: Camera, landmarks: np.ndarray, K_crop: np.ndarray) -> np.ndarray:
    """(33, 3) distorted full-image pixels + confidence -> crop pixels + confidence: through
    the lens model to the undistorted image, then `K_crop` (the crop's exact pinhole camera).
    Landmarks without a position (confidence 0 or not finite, or placed outside the image
    beyond where the lens model inverts: `Camera.undistort_points`'s `exact_only`) get
    confidence 0."""
    out = np.zeros((len(landmarks), 3), np.float32)
    ok = (landmarks[:, 2] > 0) & np.all(np.isfinite(landmarks[:, :2]), axis=1)
    if ok.any():
        xy = np.full((len(landmarks), 2), np.nan)
        xy[ok] = camera.undistort_points(landmarks[ok, :2], exact_only=True)
        ok &= np.isfinite(xy).all(axis=1)
        uvw = np.c_[xy[ok], np.ones(int(ok.sum()))] @ K_crop.T
        out[ok, :2] = uvw[:, :2] / uvw[:, 2:3]
        out[ok, 2] = landmarks[ok, 2]
    return out


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
        # The keypoint association also gives each slot's landmarks and single-view flag.
        lm_rows = pf["landmarks"][()] if "landmarks" in pf else None
        sv_rows = pf["single_view"][()] if "single_view" in pf else np.zeros(len(slot_rows), bool)
        # where each slot's view came from (the file names its source codes:
        # keypoint_association.SOURCES; '' for the hull); a projected view's landmarks are the
        # skeleton projected, not read
        sources = np.full(len(slot_rows), "", dtype=object)
        if "source" in pf:
            names = np.asarray(str(pf.attrs["sources"]).split(","), dtype=object)
            sources = names[pf["source"][()]]
        projected = sources == "projected"
        by_frame: dict[int, list[tuple[int, int, np.ndarray, float, int]]] = {}
        drop = set(job.drop_ids)
        for r, ((f, slot, pid), view) in enumerate(zip(slot_rows, view_rows, strict=True)):
            if pid in drop:
                continue
            by_frame.setdefault(int(f), []).append(
                (int(slot), int(pid), view[:4], float(view[4]), r)
            )
        result = CropJobResult(cam.name, 0, 0, 0, 0.0)
        visible: dict[int, set[int]] | None = None
        if job.visible_views is not None:
            visible = {}
            for f, p in job.visible_views:
                visible.setdefault(int(f), set()).add(int(p))
        truth = IdMaskFile(job.truth_masks, cam.name) if job.truth_masks else None
        with CropStoreWriter(
            job.part,
            list(job.camera_names),
            job.crop_size,
            job.settings,
            compression=job.compression,
            compression_level=job.compression_level,
            landmarks=lm_rows is not None,
        ) as part:
            done = {f for f, c in part.done_pairs() if c == job.camera_index}
            todo = [f for f in job.frames if f not in done]
            with_people = [f for f in todo if f in by_frame]
            pending: list[CropBatch] = []
            pending_done: list[tuple[int, int]] = []

            def flush() -> None:
                batch = (
                    CropBatch.concat(pending)
                    if pending
                    else CropBatch.empty(job.crop_size, lm_rows is not None)
                )
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
                    for slot, pid, extra_box, support, r in by_frame[f]:
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
                                np.array([sv_rows[r]], bool),
                                None
                                if lm_rows is None
                                else landmarks_to_crop(cam, lm_rows[r], Kc)[None],
                                None if lm_rows is None else projected[r : r + 1],
                            )
                        )
                        if gt is not None:
                            tid, iou = score_against_truth(pmask, gt, gt_areas)
                            scored.append(CropTruth(f, cam.name, pid, tid, iou, sources[r]))
                if gt is not None:
                    big = set(
                        np.nonzero(gt_areas >= job.min_truth_fraction * gt.size)[0].tolist()
                    ) - {0}
                    result.truth_views += len(big)
                    result.truth_views_missed += len(big - {r.truth_id for r in scored})
                    result.truth.extend(scored)
                    if visible is not None:
                        want = visible.get(f, set())
                        result.visible_views += len(want)
                        result.visible_views_missed += len(want - {r.truth_id for r in scored})
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
