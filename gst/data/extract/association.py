"""Extraction phase 2, all cameras at once and in time order: the visual hull finds the people
of each frame, ids persist over time (and id fragments are linked offline), and every camera's
labels become person labels, written to `persons_<camera>.h5` in the work folder.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from calibration import Camera, Rig
from gst.atomic import PendingFile
from gst.data.association import (
    AssociationConfig,
    CaptureVolume,
    PersonTracker,
    VoxelGrid,
    associate_frame,
    link_tracklets,
)
from gst.data.extract.options import ExtractError


@dataclass
class AssociationSummary:
    """Who was found: the processed frames, the person ids in each, the voxel count of the
    hull grid, the ids seen too briefly to crop, and the cameras that took part."""

    frames: list[int]
    ids: list[list[int]]
    voxels: int
    short_tracks: list[int]
    active: list[str]

    @classmethod
    def empty(cls, frames: list[int]) -> AssociationSummary:
        return cls(list(frames), [[] for _ in frames], 0, [], [])

    def frames_with_people(self) -> int:
        short = set(self.short_tracks)
        return sum(1 for ids in self.ids if set(ids) - short)


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
) -> AssociationSummary:
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
    pending = {n: PendingFile(out_dir / f"persons_{n}.h5") for n in names}
    outs = {}
    slots: dict[str, list[tuple[int, int, int]]] = {n: [] for n in names}
    views: dict[str, list[tuple[float, ...]]] = {n: [] for n in names}  # box x0 y0 x1 y1, support
    per_frame: list[list[int]] = []
    observed: dict[int, list[tuple[int, np.ndarray]]] = {}  # id -> (frame position, ground)
    try:
        for n in names:
            w, h = work_sizes[n]
            outs[n] = h5py.File(pending[n].path, "w")
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
            assoc = associate_frame(grid, labels)
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
            pending[n].commit()
    finally:
        for f in inputs.values():
            f.close()
        for f in outs.values():
            if f.id.valid:
                f.close()
        for file in pending.values():
            file.abort()  # no-op for committed files
    counts: dict[int, int] = {}
    for ids in per_frame:
        for i in ids:
            counts[i] = counts.get(i, 0) + 1
    # a clip shorter than min_track_frames keeps whoever is seen in all its frames
    need = min(config.min_track_frames, len(per_frame))
    short = sorted(i for i, c in counts.items() if c < need and not global_ids)
    return AssociationSummary(
        frames=list(frames),
        ids=per_frame,
        voxels=len(grid) if grid is not None else 0,
        short_tracks=short,
        active=names,
    )
