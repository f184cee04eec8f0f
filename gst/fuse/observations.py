"""What the fusion reads: per-crop 2D landmarks with each crop's exact camera, grouped per person.

Input is the crop store (gst.data.store): per crop `K_crop`, `R`, `t`, `frame`, `person_id`,
`camera`. Landmarks are BlazePose's 33 (MediaPipe order) in crop pixels with a confidence
(visibility x presence). `crop_landmarks` is the one place they come from: the store's
`landmarks` dataset when it has one, else BlazePose on each crop, refined
(`gst.detect.crops.detect_crop_landmarks(refine=True)`: a second pass on the region the first
pass's alignment keypoints give, averaged with its mirror; on the tuning workspaces it lowers the
fused body's MPJPE by 14 %, docs/fuse.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import h5py
import numpy as np

from gst.data.store import CropStore

__all__ = [
    "PersonObservations",
    "READABLE_CONFIDENCE",
    "READABLE_LANDMARKS",
    "crop_landmarks",
    "group_by_person",
    "N_LANDMARKS",
    "without_projected",
]

N_LANDMARKS = 33
# a view the fit can start from shows at least this many landmarks above this confidence
READABLE_LANDMARKS = 4
READABLE_CONFIDENCE = 0.3


def without_projected(landmarks: np.ndarray, projected: np.ndarray | None) -> np.ndarray:
    """`landmarks` (N, 33, 3) with no confidence on the rows `projected` (N,) marks as the
    rig's skeleton projected into the view rather than read (a copy where it changes any)."""
    if projected is None or not np.any(projected):
        return landmarks
    out = np.array(landmarks, copy=True)
    out[np.asarray(projected, bool), :, 2] = 0.0
    return out


def crop_landmarks(
    store: CropStore,
    rows: np.ndarray | None = None,
    progress=None,
    refine: bool = True,
    masked: bool = False,
) -> np.ndarray:
    """(N, 33, 3) landmarks of the store's `rows` (default all): u, v in crop pixels, confidence
    (0 where the store says they were projected from the rig's skeleton, not read).
    `refine` and `masked` (dim what lies outside the crop's person mask): see
    gst.detect.crops.detect_crop_landmarks; both ignored when the store holds landmarks."""
    rows = np.arange(len(store)) if rows is None else np.asarray(rows, np.int64)
    stored = store.read_landmarks(rows)  # written by the keypoint extraction
    if stored is not None:
        # Where the landmark model did not confirm a person, the extraction projected its
        # skeleton into the view: no reading of the crop, and projections of one skeleton agree
        # with each other perfectly, so they would outvote every real reading
        # (docs/fuse.md "Five-person crowds"). No confidence here; crowded crops are read again.
        return without_projected(stored, store.read_landmarks_projected(rows))
    from gst.detect.blazepose import BlazePose
    from gst.detect.crops import detect_crop_landmarks

    model = BlazePose(threads=1)
    out = np.zeros((len(rows), N_LANDMARKS, 3), np.float32)
    chunks = range(0, len(rows), 64)
    if progress is not None:
        chunks = progress(chunks, description="BlazePose landmarks in crops", total=len(chunks))
    for a in chunks:
        batch = store.read(rows[a : a + 64])  # store images are BGR
        out[a : a + len(batch)] = detect_crop_landmarks(
            batch.images, model, rgb=False, refine=refine, masks=batch.masks if masked else None
        ).with_confidence()
    return out


@dataclass
class PersonObservations:
    """One person's landmarks over the frames they were seen in, on the rig's C cameras.

    Missing views have NaN pixels, zero confidence and identity cameras."""

    person_id: int
    frames: np.ndarray  # (T,) int
    uv: np.ndarray  # (T, C, 33, 2) crop pixels
    confidence: np.ndarray  # (T, C, 33)
    K: np.ndarray  # (T, C, 3, 3) crop intrinsics
    Rt: np.ndarray  # (T, C, 3, 4) world to camera
    px_scale: np.ndarray  # (T, C) crop pixel -> full-image pixel (crop side / crop size)
    rows: np.ndarray  # (T, C) store row, -1 where the camera has no crop of this person

    @property
    def seen(self) -> np.ndarray:
        """(T, C) bool: the camera has a crop of this person in that frame."""
        return self.rows >= 0

    @property
    def readable(self) -> bool:
        """Some view in some frame shows READABLE_LANDMARKS landmarks above READABLE_CONFIDENCE:
        something to fit. People whose every landmark was projected from a skeleton, or read
        with no confidence, are not."""
        # a landmark with NaN pixels is no reading, whatever its confidence
        read = (self.confidence > READABLE_CONFIDENCE) & np.isfinite(self.uv).all(-1)
        confident = (read.sum(-1) * self.seen).max(initial=0)
        return bool(confident >= READABLE_LANDMARKS)

    def select(self, keep: np.ndarray) -> PersonObservations:
        return PersonObservations(
            self.person_id,
            *(getattr(self, k)[keep] for k in ("frames", "uv", "confidence", "K", "Rt")),
            self.px_scale[keep],
            self.rows[keep],
        )


def group_by_person(
    store: CropStore,
    landmarks: np.ndarray | Callable[[CropStore, np.ndarray], np.ndarray] | None = None,
) -> list[PersonObservations]:
    """All people of a store, sorted by id, with their landmarks per frame and camera.

    `landmarks`: (len(store), 33, 3) array, a function (store, rows) -> array, or None for
    `crop_landmarks`.
    """
    n = len(store)
    if n == 0:
        return []
    rows = np.arange(n)
    if landmarks is None:
        lm = crop_landmarks(store, rows)
    elif callable(landmarks):
        lm = landmarks(store, rows)
    else:
        lm = np.asarray(landmarks, np.float32)
    if lm.shape != (n, N_LANDMARKS, 3):
        raise ValueError(
            f"{store.path}: landmarks have shape {lm.shape}, expected ({n}, {N_LANDMARKS}, 3)"
        )
    with h5py.File(store.path, "r") as f:
        K = f["K_crop"][:n]
        R = f["R"][:n]
        t = f["t"][:n]
        side = f["crop_box"][:n, 2]
    frame = store.index.column("frame").to_numpy()
    person = store.index.column("person_id").to_numpy()
    cam = store.index.column("camera_index").to_numpy()
    C = len(store.camera_names)
    out = []
    for pid in np.unique(person):
        mine = np.flatnonzero(person == pid)
        frames = np.unique(frame[mine])
        T = len(frames)
        ti = np.searchsorted(frames, frame[mine])
        obs = PersonObservations(
            person_id=int(pid),
            frames=frames.astype(np.int64),
            uv=np.full((T, C, N_LANDMARKS, 2), np.nan, np.float64),
            confidence=np.zeros((T, C, N_LANDMARKS), np.float64),
            K=np.broadcast_to(np.eye(3), (T, C, 3, 3)).copy(),
            Rt=np.broadcast_to(np.eye(3, 4), (T, C, 3, 4)).copy(),
            px_scale=np.ones((T, C)),
            rows=np.full((T, C), -1, np.int64),
        )
        ci = cam[mine]
        obs.uv[ti, ci] = lm[mine, :, :2]
        obs.confidence[ti, ci] = np.clip(np.nan_to_num(lm[mine, :, 2]), 0, 1)
        obs.K[ti, ci] = K[mine]
        obs.Rt[ti, ci] = np.concatenate([R[mine], t[mine, :, None]], -1)
        obs.px_scale[ti, ci] = side[mine] / store.crop_size
        obs.rows[ti, ci] = mine
        out.append(obs)
    return out
