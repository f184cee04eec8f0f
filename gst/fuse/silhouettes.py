"""Where people are in each crop: evidence for the fusion that does not come from landmarks.

For every crop of the store, the union of all person masks of its camera and frame (its own and
everyone else's crops), resampled into the crop's window on a coarse grid; the part of the window
that lies outside the image counts as covered (nothing is known there). A 3D point that projects
onto nobody in most views is not a point of a body: when the landmark model reads a kicking leg's
ankle on the floor in half the views, the ankle that those views agree on lands on bare floor in
the other half, while the true ankle lies on the person in (nearly) every view. The union, not
the person's own mask, because a limb hidden behind someone else is covered by that person.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from gst.data.store import CropStore

__all__ = [
    "SILHOUETTE_SIZE",
    "CropSilhouettes",
    "ViewSilhouettes",
    "crop_silhouettes",
    "crop_windows",
    "into_window",
    "view_groups",
]

SILHOUETTE_SIZE = 64  # grid cells across a crop (a 256-px crop: 4 px a cell)


def crop_windows(store: CropStore) -> np.ndarray:
    """(N, 3) each crop row's window in its undistorted image: x0, y0, side (full-image px)."""
    index = store.index
    return np.stack(
        [
            index.column(k).to_numpy().astype(np.float64)
            for k in ("crop_x0", "crop_y0", "crop_side")
        ],
        axis=1,
    )


def view_groups(store: CropStore) -> list[np.ndarray]:
    """The store's rows grouped by camera and frame (one array of rows per view of a frame)."""
    frame = store.index.column("frame").to_numpy()
    cam = store.index.column("camera_index").to_numpy()
    order = np.lexsort((frame, cam))
    key = np.stack([cam[order], frame[order]], 1)
    starts = np.flatnonzero(np.r_[True, np.any(key[1:] != key[:-1], axis=1), True])
    return [order[a:b] for a, b in zip(starts[:-1], starts[1:], strict=True)]


def into_window(image: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A (size, size) image of the crop window `source` (x0, y0, side) resampled into the window
    `target` of the same camera and frame, at the same size (0 where `source` does not reach)."""
    size = image.shape[0]
    s = target[2] / source[2]  # target's pixels in source's pixels
    du = (target[0] - source[0]) / source[2] * size + 0.5 * s - 0.5
    dv = (target[1] - source[1]) / source[2] * size + 0.5 * s - 0.5
    inverse = np.array([[s, 0.0, du], [0.0, s, dv]])
    return cv2.warpAffine(
        image, inverse, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0
    )


def crop_silhouettes(
    store: CropStore,
    image_sizes: dict[str, tuple[int, int]],
    size: int = SILHOUETTE_SIZE,
    coverage: float = 0.25,
    progress=None,
) -> CropSilhouettes:
    """Per crop row of the store, (size, size) bool: the cells of its window covered by any
    person of its camera and frame (a cell counts when `coverage` of it is masked), or outside
    the image. `image_sizes`: camera name -> (width, height) of the undistorted image the crop
    boxes are in. Kept as bits: 512 bytes a crop at the default size. `progress`: an optional
    wrapper of iterables (description=, total=), as the pipeline's."""
    if size % 8:
        raise ValueError(f"crop_silhouettes: size must be a multiple of 8, got {size}")
    missing = sorted(set(store.camera_names) - set(image_sizes))
    if missing:
        raise ValueError(f"{store.path}: no image size for camera(s) {missing}")
    n = len(store)
    out = np.zeros((n, size, size // 8), np.uint8)
    if n == 0:
        return CropSilhouettes(out, size, store.crop_size)
    boxes = crop_windows(store)
    cam = store.index.column("camera_index").to_numpy()
    centres = (np.arange(size) + 0.5) / size  # cell centres as a share of the window
    groups = view_groups(store)
    if progress is not None:
        groups = progress(groups, description="people per view", total=len(groups))
    for rows in groups:
        width, height = image_sizes[store.camera_names[int(cam[rows[0]])]]
        # each mask's coverage on its own coarse grid, then resampled into the others' windows
        coarse = [
            cv2.resize(m.astype(np.float32) / 255.0, (size, size), interpolation=cv2.INTER_AREA)
            for m in store.read_masks(rows)
        ]
        for i in rows:
            x0, y0, side = boxes[i]
            union = np.zeros((size, size), np.float32)
            for j, cov in zip(rows, coarse, strict=True):
                np.maximum(union, into_window(cov, boxes[j], boxes[i]), out=union)
            xs, ys = x0 + centres * side, y0 + centres * side
            outside = ((ys < 0) | (ys >= height))[:, None] | ((xs < 0) | (xs >= width))[None, :]
            out[i] = np.packbits((union >= coverage) | outside, axis=-1)
    return CropSilhouettes(out, size, store.crop_size)


@dataclass
class CropSilhouettes:
    """The coarse silhouette of each crop row of a store (see crop_silhouettes), as bits."""

    bits: np.ndarray  # (N, size, size // 8) uint8, np.packbits along the last axis
    size: int  # cells across a crop
    crop_size: int  # pixels across a crop
    _fields: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_masks(cls, masks: np.ndarray, crop_size: int) -> CropSilhouettes:
        """From (N, size, size) bool silhouettes."""
        masks = np.asarray(masks, bool)
        return cls(np.packbits(masks, axis=-1), masks.shape[-1], crop_size)

    @property
    def masks(self) -> np.ndarray:
        """(N, size, size) bool (unpacked: 8 times the memory of `bits`)."""
        return np.unpackbits(self.bits, axis=-1, count=self.size).astype(bool)

    def fields(self) -> np.ndarray:
        """`distance_fields()`, computed once."""
        if self._fields is None:
            self._fields = self.distance_fields()
        return self._fields

    def distance_fields(self, size: int = 32) -> np.ndarray:
        """(N, 3, size, size) float32 per crop: crop pixels from each cell centre to the nearest
        covered cell (0 on people), and its derivatives along u and v. Coarser than the masks:
        a distance is smooth, and the body fit holds one field per person-frame and camera."""
        out = np.zeros((len(self.bits), 3, size, size), np.float32)
        cell = self.crop_size / self.size  # crop px per mask cell
        for k, packed in enumerate(self.bits):
            m = np.unpackbits(packed, axis=-1, count=self.size).astype(bool)
            if not m.any():
                continue  # nobody to measure from: no evidence
            d = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 5) * cell
            d = cv2.resize(d, (size, size), interpolation=cv2.INTER_AREA)
            gv, gu = np.gradient(d, self.crop_size / size)
            out[k] = d, gu, gv
        return out

    def for_views(self, rows: np.ndarray, points_per_frame: int) -> ViewSilhouettes:
        """The silhouettes of one person's views, `rows` (T, C) store rows (-1: no crop), for
        T x `points_per_frame` points ordered frame by frame."""
        rows = np.asarray(rows, np.int64)
        bits = self.bits if len(self.bits) else np.zeros((1, self.size, self.size // 8), np.uint8)
        return ViewSilhouettes(
            bits[np.clip(rows, 0, len(bits) - 1)],
            rows >= 0,
            np.repeat(np.arange(len(rows)), points_per_frame),
            self.crop_size,
        )


@dataclass
class ViewSilhouettes:
    """Silhouettes of the views of a batch of points: point k is seen from the views of frame
    `frame_of[k]`, whose silhouettes are `bits[frame_of[k]]` (C views, size x size cells of a
    crop of `crop_size` pixels, packed along u); `has[t, c]` is False where that view has no
    crop."""

    bits: np.ndarray  # (T, C, size, size // 8) uint8
    has: np.ndarray  # (T, C) bool
    frame_of: np.ndarray  # (N,) int
    crop_size: int

    @classmethod
    def from_masks(cls, masks, has, frame_of, crop_size: int) -> ViewSilhouettes:
        """From (T, C, size, size) bool silhouettes."""
        return cls(np.packbits(np.asarray(masks, bool), axis=-1), has, frame_of, crop_size)

    def covered(self, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(n, ..., C) bool: the view has a crop and its silhouette covers the crop pixels `uv`
        (n, ..., C, 2) of points `points` (n,); NaN pixels are never covered, pixels outside
        the crop always are (nothing is known there)."""
        size = 8 * self.bits.shape[-1]
        t = self.frame_of[np.asarray(points)]
        t = t.reshape(t.shape + (1,) * (uv.ndim - 2))
        c = np.arange(uv.shape[-2])
        # crop pixel centres are integers (gst.data.crop): cell k spans crop pixels
        # [k f - 0.5, (k + 1) f - 0.5) for f crop pixels per cell, as INTER_AREA pooled them
        cell = np.floor((np.nan_to_num(uv, nan=-1e9) + 0.5) * (size / self.crop_size))
        cell = np.clip(cell, -1, size).astype(np.int64)
        inside = ((cell >= 0) & (cell < size)).all(-1)
        u, v = np.clip(cell[..., 0], 0, size - 1), np.clip(cell[..., 1], 0, size - 1)
        hit = (self.bits[t, c, v, u >> 3] >> (7 - (u & 7))) & 1 > 0
        finite = np.isfinite(uv).all(-1)
        return self.has[t, c] & finite & np.where(inside, hit, True)
