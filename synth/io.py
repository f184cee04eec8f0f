"""Deterministic, atomic file writers for scene folders (no timestamps in any file)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gst.atomic import PendingFile, atomic_path


def write_json(path: Path, data) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def write_parquet(path: Path, table: pa.Table) -> None:
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")


def write_png(path: Path, image: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"could not write PNG {path}")


class VideoOut:
    """An mp4 (MPEG-4 part 2, 'mp4v') written frame by frame, renamed into place on close."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        if width % 2 or height % 2 or max(width, height) > 8190:
            # mp4v drops an odd last column or row (the video a pixel smaller than the
            # calibration and truth written beside it) and opens no writer at 8192
            raise ValueError(
                f"{path}: frame size {width}x{height}: width and height must be even and at most "
                "8190 for mp4v video"
            )
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = PendingFile(self.path)
        self._size = (width, height)
        self._writer = cv2.VideoWriter(
            str(self._file.path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height)
        )
        if not self._writer.isOpened():
            self._file.abort()
            raise OSError(
                f"OpenCV cannot open an mp4v writer for {self.path} (is FFmpeg available in cv2?)"
            )
        self.frames = 0

    def write(self, bgr: np.ndarray) -> None:
        if bgr.shape != (self._size[1], self._size[0], 3) or bgr.dtype != np.uint8:
            raise ValueError(
                f"{self.path.name}: frame {bgr.shape} {bgr.dtype}, expected "
                f"({self._size[1]}, {self._size[0]}, 3) uint8"
            )
        self._writer.write(bgr)
        self.frames += 1

    def close(self) -> None:
        self._writer.release()
        self._file.commit()

    def abort(self) -> None:
        self._writer.release()
        self._file.abort()


class MaskStore:
    """Per-camera HDF5 of person-id masks (T, H, W) uint8 and optional person depth float32,
    one gzip chunk per frame."""

    def __init__(
        self, path: Path, n_frames: int, width: int, height: int, camera: str, with_depth: bool
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = PendingFile(self.path)
        self._f = h5py.File(self._file.path, "w", track_order=False)
        self._f.attrs["camera"] = camera
        self._f.attrs["mask_values"] = "0 = background, k = person_id k"
        self.mask = self._frames("mask", n_frames, height, width, np.uint8)
        self.depth = None
        if with_depth:
            self.depth = self._frames("depth", n_frames, height, width, np.float32)
            self.depth.attrs["units"] = "m, camera z; 0 where the mask is 0"

    def _frames(self, name: str, n_frames: int, height: int, width: int, dtype) -> h5py.Dataset:
        """A (T, H, W) dataset, one gzip chunk per frame."""
        return self._f.create_dataset(
            name,
            (n_frames, height, width),
            dtype,
            chunks=(1, height, width),
            compression="gzip",
            compression_opts=4,
            shuffle=True,
            track_times=False,
        )

    def write(self, frame: int, mask: np.ndarray, depth: np.ndarray | None) -> None:
        self.mask[frame] = mask
        if self.depth is not None:
            self.depth[frame] = np.where(mask > 0, depth, 0).astype(np.float32)

    def close(self) -> None:
        self._f.close()
        self._file.commit()

    def abort(self) -> None:
        self._f.close()
        self._file.abort()


def read_masks(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(masks (T, H, W) uint8, depth (T, H, W) float32 or None) from a truth/masks file."""
    with h5py.File(path, "r") as f:
        if "mask" not in f:
            raise KeyError(f"{path}: no 'mask' dataset (expected a synth truth/masks file)")
        return f["mask"][...], (f["depth"][...] if "depth" in f else None)
