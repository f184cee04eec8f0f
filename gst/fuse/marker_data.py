"""BlazePose detections on rendered synthetic crops, with the truth body of every crop: the
data the virtual-marker model (gst.body.markers) is fitted on (`gst.fuse.fit_markers`).

`MarkerData` files are made by `python -m gst.lift.marker_worlds --seed 5000 --out DIR`
(rendered tuning worlds, seeds 5000+ only).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gst.atomic import atomic_save_npz
from gst.fuse.observations import N_LANDMARKS

__all__ = ["MarkerData", "load_marker_data", "people_from_marker_data"]


@dataclass
class MarkerData:
    """One row per (frame, truth person, camera) crop."""

    landmarks: np.ndarray  # (N, 33, 3) crop px + confidence
    K: np.ndarray  # (N, 3, 3) crop intrinsics
    R: np.ndarray  # (N, 3, 3)
    t: np.ndarray  # (N, 3)
    px_scale: np.ndarray  # (N,) crop px -> full-image px
    frame: np.ndarray  # (N,)
    person: np.ndarray  # (N,) truth person id
    camera: np.ndarray  # (N,)
    world: np.ndarray  # (N,) world (seed) id
    betas: np.ndarray  # (N, nb)
    global_orient: np.ndarray  # (N, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (N, 23, 3)
    transl: np.ndarray  # (N, 3)

    def save(self, path: Path) -> None:
        atomic_save_npz(path, compressed=True, **self.__dict__)


def load_marker_data(paths: list[Path]) -> MarkerData:
    parts = []
    for p in paths:
        with np.load(p, allow_pickle=False) as z:
            parts.append({k: z[k] for k in z.files})
    return MarkerData(**{k: np.concatenate([d[k] for d in parts]) for k in parts[0]})


def people_from_marker_data(data: MarkerData, world: int):
    """One world's detections as `PersonObservations` per truth person (ids are the truth ids),
    for tuning the fit on worlds with truth. Returns (people, truth rows (T,) per person)."""
    from gst.fuse.observations import PersonObservations

    sel = np.flatnonzero(data.world == world)
    C = int(data.camera.max()) + 1
    people, rows = [], []
    for pid in np.unique(data.person[sel]):
        mine = sel[data.person[sel] == pid]
        frames = np.unique(data.frame[mine])
        T = len(frames)
        ti = np.searchsorted(frames, data.frame[mine])
        ci = data.camera[mine]
        obs = PersonObservations(
            int(pid),
            frames.astype(np.int64),
            np.full((T, C, N_LANDMARKS, 2), np.nan),
            np.zeros((T, C, N_LANDMARKS)),
            np.broadcast_to(np.eye(3), (T, C, 3, 3)).copy(),
            np.broadcast_to(np.eye(3, 4), (T, C, 3, 4)).copy(),
            np.ones((T, C)),
            np.full((T, C), -1, np.int64),
        )
        obs.uv[ti, ci] = data.landmarks[mine, :, :2]
        obs.confidence[ti, ci] = data.landmarks[mine, :, 2]
        obs.K[ti, ci] = data.K[mine]
        obs.Rt[ti, ci] = np.concatenate([data.R[mine], data.t[mine, :, None]], -1)
        obs.px_scale[ti, ci] = data.px_scale[mine]
        obs.rows[ti, ci] = mine
        first = np.zeros(T, np.int64)
        first[ti] = mine
        people.append(obs)
        rows.append(first)
    return people, rows
