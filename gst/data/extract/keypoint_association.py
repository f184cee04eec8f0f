"""Extraction phase 2 by keypoints: all cameras at once and in time order, the person instances
of phase 1 (BlazePose landmarks per camera) are matched across the calibrated views, tracked in
3D, looked at again with their neighbours painted out, and turned into per-camera person label
images (`gst.data.keypoints.CrowdTracker`), written to `persons_<camera>.h5` like the
visual-hull path, plus each slot's landmarks and whether one camera only saw that person.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

import h5py
import numpy as np

from calibration import Camera, Rig
from gst.atomic import PendingFile
from gst.cores import available_cores
from gst.data.extract.association import AssociationSummary
from gst.data.extract.options import ExtractError
from gst.data.keypoints import PersonInstance
from gst.data.keypoints.people import CrowdConfig, CrowdTracker, FramePeople
from gst.detect.blazepose import BlazePose
from gst.detect.persons import skeleton_support
from gst.video import read_frames

log = logging.getLogger("gst.data")
SOURCES = {"detected": 0, "refined": 1, "projected": 2, "single": 3}
SKELETON_WIDTH = 0.08  # a region's mask stays within this share of its side of the skeleton


def _landmark_segmenter(models_dir: str | None, workers: int):
    """The landmark model as `CrowdTracker` calls it from its `workers` threads: landmarks,
    presence and the person probability near that person's own skeleton (as
    `PersonSegmenter` keeps it). One interpreter per thread (they are not thread-safe); the
    association runs alone in this process after phase 1, so they share the cores (same
    numbers for any thread count)."""
    local = threading.local()
    threads = max(1, min(4, available_cores()) // workers)

    def segment(camera: str, image: np.ndarray, roi, origin=(0, 0)):
        model = getattr(local, "model", None)
        if model is None:
            model = local.model = BlazePose(models_dir, threads=threads)
        s = model.segment(image, roi)
        h, w = image.shape[:2]
        lm = s.landmarks[:, :2]
        # A degenerate region can give landmarks that are not numbers or far off the image.
        if not np.all(np.isfinite(lm)) or np.abs(lm).max() > 10 * max(h, w):
            return None
        near = skeleton_support(s.landmarks, image.shape[:2], SKELETON_WIDTH * roi.side)
        return s.landmarks, s.presence, np.where(near, s.probability, 0.0)

    return segment


def _frame_instances(f: h5py.File, i: int, sx: float, sy: float, name: str):
    """Phase 1's instances of frame row `i` of one camera: PersonInstances (full-resolution
    landmarks and boxes) and their masks (work resolution)."""
    labels = f["labels"][i]
    # phase 1 keeps landmarks for MAX_INSTANCES people: labels past them have none (crowds)
    n = min(int(labels.max()), f["landmarks"].shape[1])
    lms, pres = f["landmarks"][i, :n], f["presence"][i, :n]
    insts, masks = [], []
    for k in range(n):
        m = labels == k + 1
        ys, xs = np.nonzero(m)
        # the mask's outer pixel edges in full-resolution pixel-centre coordinates, as
        # PersonInstance boxes from landmarks are
        box = (
            (
                xs.min() / sx - 0.5,
                ys.min() / sy - 0.5,
                (xs.max() + 1) / sx - 0.5,
                (ys.max() + 1) / sy - 0.5,
            )
            if len(xs)
            else None
        )
        insts.append(PersonInstance.create(lms[k], box, float(pres[k]), where=f"camera {name}"))
        masks.append(m)
    return insts, masks


def _extra_box(
    lm: np.ndarray, sx: float, sy: float, size: tuple[int, int], min_confidence: float
) -> tuple[float, float, float, float]:
    """Work-resolution box (pixel edges) of a view's landmarks: the crop covers the whole person
    even where their mask is cut by someone in front. `size`: the full-resolution frame (w, h).
    A landmark outside the frame counts only at `min_confidence` or more: the model places the
    limbs the frame's edge cuts off beyond it with a visibility near 0, and those grew the box
    by up to 2.6 times (the person shrank in their crop by as much)."""
    w, h = size
    inside = (lm[:, 0] >= -0.5) & (lm[:, 0] <= w - 0.5) & (lm[:, 1] >= -0.5) & (lm[:, 1] <= h - 0.5)
    seen = (lm[:, 2] > 0) & (inside | (lm[:, 2] >= min_confidence))
    if seen.sum() < 2:
        return (np.nan,) * 4
    lo, hi = lm[seen, :2].min(axis=0), lm[seen, :2].max(axis=0)
    return ((lo[0] + 0.5) * sx, (lo[1] + 0.5) * sy, (hi[0] + 0.5) * sx, (hi[1] + 0.5) * sy)


def associate_scene_keypoints(
    label_files: dict[str, Path],
    cameras: Rig | list[Camera],
    videos: dict[str, Path],
    work_sizes: dict[str, tuple[int, int]],
    frames: list[int],
    out_dir: Path,
    config: CrowdConfig,
    models_dir: str | None = None,
    min_track_frames: int = 5,
    progress: Callable | None = None,
    step_seconds: float = 1 / 30,
) -> AssociationSummary:
    """Per-frame people and per-camera person labels, written to `out_dir/persons_<cam>.h5`
    (datasets as the visual-hull path, plus `landmarks` (slots, 33, 3) full-resolution
    distorted pixels and confidence, `single_view` and `source` per slot)."""
    names = [c.name for c in cameras]
    inputs = {n: h5py.File(label_files[n], "r") for n in names}
    try:
        missing = [n for n in names if "landmarks" not in inputs[n]]
        if missing:
            raise ExtractError(
                f"camera(s) {missing}: phase 1 kept no landmarks (external masks or boxes?); "
                "the keypoint association needs BlazePose instances on every camera"
            )
        sxy = {
            c.name: (work_sizes[c.name][0] / c.width, work_sizes[c.name][1] / c.height)
            for c in cameras
        }
        # The cameras of a frame are refined on threads: the phase runs alone in this process.
        workers = min(len(names), available_cores())
        segment = _landmark_segmenter(models_dir, workers) if config.refine else None
        # One scale per camera, the width's: the work size's rounding makes the height's differ
        # by less than a work pixel across the image.
        tracker = CrowdTracker(
            cameras, step_seconds, config, segment, {n: sxy[n][0] for n in names}, workers
        )
        backgrounds = {n: inputs[n]["background"][()] for n in names}
        streams = {
            n: iter(read_frames(videos[n], frames, n, size=work_sizes[n]))
            if config.refine
            else None
            for n in names
        }
        try:
            results = _run(tracker, inputs, streams, backgrounds, frames, sxy, progress)
        finally:
            tracker.close()
        for line in tracker.counts():
            log.info("keypoint association: %s", line)
    finally:
        for f in inputs.values():
            f.close()
    full_size = {c.name: (c.width, c.height) for c in cameras}
    return _write(
        results, names, work_sizes, frames, out_dir, sxy, min_track_frames,
        full_size, config.match.min_confidence,
    )  # fmt: skip


def _run(tracker, inputs, streams, backgrounds, frames, sxy, progress) -> list[FramePeople]:
    names = list(inputs)
    out = []
    it: Iterable = enumerate(frames)
    if progress is not None:
        it = progress(it, description="associating people by keypoints", total=len(frames))
    for i, frame in it:
        insts, masks, fg, images = {}, {}, {}, {}
        for n in names:
            insts[n], masks[n] = _frame_instances(inputs[n], i, *sxy[n], n)
            fg[n] = inputs[n]["foreground"][i]
            if streams[n] is not None:
                fi, images[n] = next(streams[n])
                if fi != frame:
                    raise ExtractError(f"camera {n}: decoded frame {fi}, expected {frame}")
        out.append(tracker.process(frame, insts, fg, images or None, backgrounds, masks))
    return out


def _write(
    results, names, work_sizes, frames, out_dir, sxy, min_track_frames, full_size, min_confidence
):
    # Offline: ids seen in too few frames are not trusted: an id is kept when its multi-view
    # frames or its single-view frames reach `min_track_frames` (on the lab, 1-2 frame
    # single-view ids are duplicates of a tracked person's body or legs). Someone one camera
    # sees for a long time keeps their crops when a second camera sees them briefly (the
    # multi-view count alone dropped all of them).
    # a clip shorter than that keeps whoever is seen in all its frames (every id was dropped)
    min_track_frames = min(min_track_frames, len(results))
    frames_of: dict[int, int] = {}
    single_frames: dict[int, int] = {}
    for res in results:
        for p in res.people:
            counts = single_frames if p.single_view else frames_of
            counts[p.pid] = counts.get(p.pid, 0) + 1
    short = sorted(
        pid
        for pid in set(frames_of) | set(single_frames)
        if frames_of.get(pid, 0) < min_track_frames and single_frames.get(pid, 0) < min_track_frames
    )
    pending = {n: PendingFile(out_dir / f"persons_{n}.h5") for n in names}
    per_frame = []
    try:
        for n in names:
            w, h = work_sizes[n]
            slots, views, lms, single, source = [], [], [], [], []
            with h5py.File(pending[n].path, "w") as f:
                lab_ds = f.create_dataset(
                    "labels", shape=(len(frames), h, w), dtype="uint8", chunks=(1, h, w),
                    compression="gzip", compression_opts=1,
                )  # fmt: skip
                for i, res in enumerate(results):
                    lab = np.zeros((h, w), np.uint8)
                    slot = 0
                    for p in res.people:
                        view = p.views.get(n)
                        if view is None or slot >= 255:
                            continue
                        slot += 1
                        lab[view.mask & (lab == 0)] = slot
                        slots.append((res.frame, slot, p.pid))
                        box = _extra_box(view.landmarks, *sxy[n], full_size[n], min_confidence)
                        views.append((*box, view.visibility))
                        lms.append(view.landmarks.astype(np.float32))
                        single.append(p.single_view)
                        source.append(SOURCES[view.source])
                    lab_ds[i] = lab
                f.create_dataset("frames", data=np.asarray(frames, dtype=np.int64))
                f.create_dataset("slots", data=np.asarray(slots, np.int64).reshape(-1, 3))
                f.create_dataset("views", data=np.asarray(views, np.float64).reshape(-1, 5))
                f.create_dataset("landmarks", data=np.asarray(lms, np.float32).reshape(-1, 33, 3))
                f.create_dataset("single_view", data=np.asarray(single, bool))
                f.create_dataset("source", data=np.asarray(source, np.uint8))
                f.attrs["sources"] = ",".join(SOURCES)
            pending[n].commit()
    finally:
        for file in pending.values():
            file.abort()  # no-op for committed files
    for res in results:
        per_frame.append(sorted({p.pid for p in res.people}))
    return AssociationSummary(
        frames=list(frames), ids=per_frame, voxels=0, short_tracks=short, active=list(names)
    )
