"""Extraction phase 1, per camera: foreground label images at a reduced "work" resolution.

The background model labels moving blobs; a learned person model (BlazePose) labels person
instances instead; external masks or boxes replace both for the cameras they cover. One
picklable job per camera, so an executor can fan the cameras out.

With `instances` (the keypoint association), the file also holds what phase 2 needs besides
the labels: each instance's 33 landmarks (full-resolution distorted pixels, confidence) and
presence, the background model's foreground per frame, and the background image itself (the
clean plate's median, or the capture's) to paint people out with.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from gst.atomic import atomic_path
from gst.data.background import (
    BackgroundConfig,
    build_background,
    sample_indices,
    temporal_medians,
)
from gst.data.external import (
    IdMaskFile,
    boxes_to_labels,
    resize_labels,
)
from gst.data.masks import MaskConfig, clean_mask
from gst.detect.blazepose import BlazePose
from gst.detect.persons import PersonSegmenter, SegmenterConfig
from gst.video import VideoError, held_frames, probe_video, read_frames


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
    instances: bool = False  # also keep landmarks, foreground and background (keypoint path)


MAX_INSTANCES = 32  # instances kept per frame and camera (landmarks array width)


@dataclass(frozen=True)
class MaskJobResult:
    camera: str
    frames_with_blobs: int
    blobs: int
    seconds: float
    cached: bool


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
    sx, sy = w / job.full_size[0], h / job.full_size[1]  # per axis: the sizes are rounded
    labels = np.zeros((len(job.frames), h, w), dtype=np.uint8)
    pos = {f: i for i, f in enumerate(job.frames)}
    keep = (
        job.instances
        and job.persons is not None
        and not job.external_masks
        and job.external_boxes is None
    )
    if keep:
        landmarks = np.zeros((len(job.frames), MAX_INSTANCES, 33, 3), np.float32)
        presence = np.zeros((len(job.frames), MAX_INSTANCES), np.float32)
        foreground = np.zeros((len(job.frames), h, w), bool)
    if job.external_masks:
        ext = IdMaskFile(job.external_masks, job.camera, external=True)
        for f in job.frames:
            m = ext.get(f)
            if m is not None:
                labels[pos[f]] = resize_labels(m, (w, h))
        ext.close()
    else:
        cache: dict[int, np.ndarray] = {}
        if job.clean_plate:
            # An empty-scene clip of this camera: learn the background from it alone.
            plate = probe_video(job.clean_plate, job.camera, strict=True)
            if (plate.width, plate.height) != tuple(job.full_size):
                raise VideoError(
                    f"camera '{job.camera}' background video {job.clean_plate}: frames are "
                    f"{plate.width}x{plate.height}, the camera's video is "
                    f"{job.full_size[0]}x{job.full_size[1]}"
                )
            # the frames it holds: a container that announces one or two more (as some cameras
            # write) failed on the missing last frame as "truncated or corrupt"
            idx = sample_indices(held_frames(plate), job.background.samples)
            samples = np.stack(
                [img for _, img in read_frames(job.clean_plate, idx, job.camera, size=(w, h))]
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
            cache = dict(
                read_frames(job.video, sorted(set(idx) | set(job.frames)), job.camera, size=(w, h))
            )
            samples = np.stack([cache[i] for i in idx])
        else:
            idx = sample_indices(job.n_frames, job.background.samples)
            samples = np.stack(
                [img for _, img in read_frames(job.video, idx, job.camera, size=(w, h))]
            )
        # The model's median and the stored empty scene (numpy's median) from one partial sort.
        lower, middle = temporal_medians(samples) if keep else (None, None)
        model = build_background(samples, job.background, lower)
        if keep:
            background = middle.astype(np.uint8)
        del samples
        segmenter = None
        if job.persons is not None:
            segmenter = PersonSegmenter(BlazePose(job.persons_models_dir), job.persons)
        frames_iter = (
            ((f, cache.pop(f)) for f in job.frames)
            if cache
            else read_frames(job.video, job.frames, job.camera, size=(w, h))
        )
        for f, img in frames_iter:
            lab, blobs = clean_mask(model.foreground(img), job.masks)
            if keep:
                foreground[pos[f]] = lab > 0
            if segmenter is not None:
                lab, people = segmenter.segment(
                    img, [b.box for b in blobs] if job.persons_hints else ()
                )
                if keep:
                    for k, p in enumerate(people[:MAX_INSTANCES]):
                        lm = p.landmarks.copy()
                        # Work pixels to full-resolution pixels (centres at integers).
                        lm[:, :2] = (lm[:, :2] + 0.5) / (sx, sy) - 0.5
                        landmarks[pos[f], k] = lm
                        presence[pos[f], k] = p.presence
            if job.external_boxes is not None:
                lab = boxes_to_labels(lab, job.external_boxes.get(f, []), (w, h), (sx, sy))
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
        if keep:
            f.create_dataset("landmarks", data=landmarks, chunks=(1, MAX_INSTANCES, 33, 3))
            f.create_dataset("presence", data=presence)
            f.create_dataset(
                "foreground", data=foreground, chunks=(1, h, w), compression="gzip",
                compression_opts=1,
            )  # fmt: skip
            f.create_dataset("background", data=background)
        f.attrs.update(
            {
                "frames_with_blobs": n_with,
                "blobs": n_blobs,
                "seconds": seconds,
                "camera": job.camera,
            }
        )

    with atomic_path(out) as tmp, h5py.File(tmp, "w") as f:
        fill(f)
    return MaskJobResult(job.camera, n_with, n_blobs, seconds, False)
