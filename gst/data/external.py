"""Masks and boxes supplied from outside (any detector or annotation tool), and truth masks.

Format (docs/formats/external_masks.md), one folder:

    <root>/<camera>.h5 or <camera>.npz   person-id masks: `masks` (or `mask`) uint8
                                         (F, H, W), 0 = nobody, 1..254 = a person; optional
                                         `frames` int (F,) frame numbers (default 0..F-1)
    <root>/boxes.parquet                 optional boxes: frame, camera, x0, y0, x1, y1
                                         (pixel edges in the distorted image), optional person_id
    <root>/meta.json                     optional {"global_ids": true} when the same id means the
                                         same person in every camera

The synthetic scenes' truth masks (`<scene>/truth/masks/<camera>.npz|.h5`) use the same layout,
so `IdMaskFile` reads both. NPZ files are opened with `allow_pickle=False`.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq


class ExternalError(ValueError):
    """An external mask/box file is missing, malformed, or does not fit the videos."""


def _pick_masks_array(keys_shapes: dict[str, tuple], path: Path) -> str:
    for key in ("masks", "mask"):  # `mask` is what synth's truth/masks/<cam>.h5 holds
        if key in keys_shapes:
            return key
    three_d = [k for k, s in keys_shapes.items() if len(s) == 3]
    if len(three_d) == 1:
        return three_d[0]
    raise ExternalError(
        f"{path}: expected a dataset 'masks' of shape (frames, H, W); found {keys_shapes}"
    )


class IdMaskFile:
    """Per-frame person-id masks of one camera from an .h5 or .npz file (read lazily)."""

    def __init__(self, path: Path | str, camera: str = "", external: bool = False):
        """`external`: a user's masks, where 255 is no person id (docs/formats/external_masks.md);
        synthetic truth numbers people up to 255."""
        self.path = Path(path)
        self.camera = camera
        self.external = external
        if not self.path.is_file():
            raise ExternalError(f"camera '{camera}': mask file {self.path} not found")
        self._npz_masks: np.ndarray | None = None
        self._h5: h5py.File | None = None
        if self.path.suffix == ".npz":
            try:
                with np.load(self.path, allow_pickle=False) as z:
                    key = _pick_masks_array({k: z[k].shape for k in z.files}, self.path)
                    masks = z[key]
                    frames = z["frames"] if "frames" in z.files else np.arange(len(masks))
            except (OSError, ValueError, zipfile.BadZipFile) as exc:  # not ExternalError itself
                if isinstance(exc, ExternalError):
                    raise
                # e.g. an object array (pickled: refused) or a truncated archive
                raise ExternalError(f"camera '{camera}': cannot read {self.path} ({exc})") from exc
            self._npz_masks = masks
            self.shape = masks.shape
            self.dtype = masks.dtype
        elif self.path.suffix in (".h5", ".hdf5"):
            try:
                f = h5py.File(self.path, "r")
            except OSError as exc:
                raise ExternalError(f"camera '{camera}': cannot read {self.path} ({exc})") from exc
            with f:
                shapes = {k: f[k].shape for k in f.keys() if isinstance(f[k], h5py.Dataset)}
                self._key = _pick_masks_array(shapes, self.path)
                self.shape = f[self._key].shape
                self.dtype = f[self._key].dtype
                if "frames" in f and not isinstance(f["frames"], h5py.Dataset):
                    raise ExternalError(
                        f"camera '{camera}': {self.path} 'frames' is a group; expected a dataset "
                        "of frame numbers"
                    )
                frames = f["frames"][()] if "frames" in f else np.arange(self.shape[0])
        else:
            raise ExternalError(f"camera '{camera}': mask file {self.path} must be .h5 or .npz")
        if len(self.shape) != 3:
            raise ExternalError(
                f"camera '{camera}': {self.path} masks have shape {self.shape}, expected (F, H, W)"
            )
        if self.dtype != np.uint8:
            raise ExternalError(
                f"camera '{camera}': {self.path} masks are {self.dtype}, expected uint8 ids"
            )
        frames = np.asarray(frames).reshape(-1)
        if frames.size and not np.issubdtype(frames.dtype, np.integer):
            raise ExternalError(
                f"camera '{camera}': {self.path} frame numbers are {frames.dtype}, expected "
                "integers (0-based video frames)"
            )
        frames = frames.astype(np.int64)
        values, counts = np.unique(frames, return_counts=True)
        repeated = values[counts > 1]
        if repeated.size:
            raise ExternalError(
                f"camera '{camera}': {self.path} lists frames {repeated[:5].tolist()} more than "
                "once; each frame may have one mask"
            )
        if len(frames) != self.shape[0]:
            raise ExternalError(
                f"camera '{camera}': {self.path} has {self.shape[0]} masks but "
                f"{len(frames)} frame numbers"
            )
        self._row = {int(f): i for i, f in enumerate(frames)}

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_h5"] = None
        return state

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the masks."""
        return int(self.shape[2]), int(self.shape[1])

    @property
    def frames(self) -> list[int]:
        return sorted(self._row)

    def get(self, frame: int) -> np.ndarray | None:
        """The id mask of `frame`, or None if the file has no entry for it."""
        row = self._row.get(int(frame))
        if row is None:
            return None
        if self._npz_masks is not None:
            mask = self._npz_masks[row]
        else:
            if self._h5 is None:
                self._h5 = h5py.File(self.path, "r")
            mask = self._h5[self._key][row]
        if self.external and mask.size and mask.max() == 255:  # a binary 0/255 mask: person 255
            raise ExternalError(
                f"camera '{self.camera}': {self.path} frame {frame} holds the value 255; person "
                "ids are 1..254 (0 = nobody): write a binary mask as 0/1"
            )
        return mask

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None


def find_mask_file(folder: Path, camera: str) -> Path | None:
    for suffix in (".h5", ".hdf5", ".npz"):
        p = folder / f"{camera}{suffix}"
        if p.is_file():
            return p
    return None


@dataclass
class ExternalDetections:
    """External masks and/or boxes for some cameras. Build it with `read_external(root)`."""

    root: Path
    mask_files: dict[str, Path] = field(default_factory=dict)
    boxes: dict[str, dict[int, list[tuple[int, np.ndarray]]]] = field(default_factory=dict)
    global_ids: bool = False

    def masks(self, camera: str) -> IdMaskFile | None:
        p = self.mask_files.get(camera)
        return IdMaskFile(p, camera, external=True) if p else None

    def signature(self) -> list:
        """What identifies this input for caches and resume: each mask file by name, size and
        its whole content (SHA-256), the boxes' content and `global_ids`. A mask file replaced
        after an interrupted run (same folder name) was served from the old labels; so was one
        edited in place where a sampled digest (first and last MiB) did not look (an HDF5's
        frames in the middle: same size, same ends)."""
        import hashlib

        from gst.video import file_identity

        files = [
            [cam, *file_identity(path, whole=True)] for cam, path in sorted(self.mask_files.items())
        ]
        digest = hashlib.sha256()
        for cam in sorted(self.boxes):
            for frame in sorted(self.boxes[cam]):
                for pid, box in self.boxes[cam][frame]:
                    digest.update(f"{cam}|{frame}|{pid}|".encode())
                    digest.update(np.asarray(box, np.float64).tobytes())
        return [Path(self.root).name, files, digest.hexdigest(), bool(self.global_ids)]

    def camera_boxes(self, camera: str) -> dict[int, list[tuple[int, np.ndarray]]] | None:
        """frame -> [(person_id or -1, x0 y0 x1 y1)] for a camera, or None if it has no boxes."""
        return self.boxes.get(camera)

    def validate(self, sizes: dict[str, tuple[int, int]], n_frames: int) -> None:
        """Check that every mask file fits its camera's video (size, frame range)."""
        for cam in list(self.mask_files) + list(self.boxes):
            if cam not in sizes:
                raise ExternalError(
                    f"{self.root}: external data for camera '{cam}', which has no video "
                    f"(cameras: {sorted(sizes)})"
                )
        for cam, path in self.mask_files.items():
            m = IdMaskFile(path, cam, external=True)
            if m.size != tuple(sizes[cam]):
                raise ExternalError(
                    f"camera '{cam}': masks in {path} are {m.size[0]}x{m.size[1]}, "
                    f"the video is {sizes[cam][0]}x{sizes[cam][1]}"
                )
            bad = [f for f in m.frames if not 0 <= f < n_frames]
            if bad:
                raise ExternalError(
                    f"camera '{cam}': {path} has masks for frames {bad[:5]} outside "
                    f"the video's 0..{n_frames - 1}"
                )
        for cam, frames in self.boxes.items():
            bad = sorted(f for f in frames if not 0 <= f < n_frames)
            if bad:  # e.g. 1-based frame numbers: every box a frame late, the last one lost
                raise ExternalError(
                    f"camera '{cam}': {self.root / 'boxes.parquet'} has boxes for frames "
                    f"{bad[:5]} outside the video's 0..{n_frames - 1} (frames are 0-based)"
                )
            boxes = np.array([b for rows in frames.values() for _pid, b in rows])
            w, h = sizes[cam]
            if len(boxes) and boxes[:, 2:].max() <= 1.5:
                raise ExternalError(
                    f"camera '{cam}': {self.root / 'boxes.parquet'} boxes all lie within "
                    f"0..{boxes[:, 2:].max():.2f}: they look normalised; expected pixel edges "
                    f"of the {w}x{h} frame"
                )
            outside = (
                (boxes[:, 2] <= -0.5) | (boxes[:, 0] >= w - 0.5)
                | (boxes[:, 3] <= -0.5) | (boxes[:, 1] >= h - 0.5)
            )  # fmt: skip
            if outside.any():  # e.g. width and height swapped: the box labelled nothing
                raise ExternalError(
                    f"camera '{cam}': {self.root / 'boxes.parquet'} has {int(outside.sum())} "
                    f"boxes entirely outside the {w}x{h} frame, e.g. "
                    f"{boxes[outside][0].round(1).tolist()} (x0, y0, x1, y1 pixel edges)"
                )


def _box_person_ids(table: pa.Table, path: Path) -> np.ndarray:
    """boxes.parquet's optional `person_id` as int64, -1 where empty: an integer column, or a
    float one with whole numbers (how pandas writes integers with gaps; NaN = empty)."""
    if "person_id" not in table.column_names:
        return np.full(table.num_rows, -1, np.int64)
    col = table["person_id"]
    kind = col.type
    if pa.types.is_integer(kind):
        return np.asarray(col.fill_null(-1).to_numpy(), np.int64)
    if pa.types.is_floating(kind):
        v = col.to_numpy(zero_copy_only=False).astype(np.float64)
        whole = np.isnan(v) | (np.isfinite(v) & (v == np.round(v)))
        if whole.all():
            return np.where(np.isnan(v), -1, v).astype(np.int64)
        bad = int(np.flatnonzero(~whole)[0])
        raise ExternalError(
            f"{path}: column 'person_id' row {bad} is {v[bad]}; expected whole numbers "
            "(empty = unknown)"
        )
    raise ExternalError(
        f"{path}: column 'person_id' is {kind}; expected integers (empty = unknown)"
    )


def read_external(root: Path | str, cameras: list[str]) -> ExternalDetections:
    """Read the external masks/boxes folder (format in the module docstring)."""
    root = Path(root)
    if not root.is_dir():
        raise ExternalError(f"external masks folder {root} does not exist")
    ext = ExternalDetections(root)
    for cam in cameras:
        p = find_mask_file(root, cam)
        if p is not None:
            ext.mask_files[cam] = p
    strays = sorted(
        f.name
        for f in root.iterdir()
        if f.suffix in (".h5", ".hdf5", ".npz") and f.stem not in cameras
    )
    if strays:  # a misnamed camera's masks would be skipped, that camera falling back quietly
        raise ExternalError(
            f"{root}: mask files {strays} are named after no camera; expected <camera>.h5 / "
            f".npz with the cameras {cameras}"
        )
    meta = root / "meta.json"
    if meta.is_file():
        try:
            info = json.loads(meta.read_text())
        except json.JSONDecodeError as exc:
            raise ExternalError(f"{meta}: invalid JSON ({exc})") from exc
        if not isinstance(info, dict) or not set(info) <= {"global_ids"}:
            raise ExternalError(
                f"{meta}: expected an object with optional key 'global_ids', got {info!r}"
            )
        global_ids = info.get("global_ids", False)
        if not isinstance(global_ids, bool):
            raise ExternalError(
                f"{meta}: global_ids is {global_ids!r}, expected true or false (a JSON boolean)"
            )
        ext.global_ids = global_ids
    boxes_path = root / "boxes.parquet"
    if boxes_path.is_file():
        table = pq.read_table(boxes_path)
        need = {"frame", "camera", "x0", "y0", "x1", "y1"}
        if not need <= set(table.column_names):
            raise ExternalError(
                f"{boxes_path}: missing columns {sorted(need - set(table.column_names))}; "
                f"has {table.column_names}"
            )
        if not pa.types.is_integer(table.schema.field("frame").type) or table["frame"].null_count:
            raise ExternalError(
                f"{boxes_path}: column 'frame' is {table.schema.field('frame').type} with "
                f"{table['frame'].null_count} nulls; expected integers (0-based video frames)"
            )
        if table["camera"].null_count:
            raise ExternalError(
                f"{boxes_path}: column 'camera' has {table['camera'].null_count} empty rows; "
                "every box names its camera"
            )
        cols = {k: table.column(k).to_pylist() for k in table.column_names}
        pid = _box_person_ids(table, boxes_path)
        for i in range(table.num_rows):
            box = np.array([cols[k][i] for k in ("x0", "y0", "x1", "y1")], dtype=np.float64)
            if not (np.all(np.isfinite(box)) and box[2] > box[0] and box[3] > box[1]):
                raise ExternalError(
                    f"{boxes_path}: row {i} (camera {cols['camera'][i]}, frame "
                    f"{cols['frame'][i]}) has an invalid box {box.tolist()}"
                )
            ext.boxes.setdefault(str(cols["camera"][i]), {}).setdefault(
                int(cols["frame"][i]), []
            ).append((int(pid[i]), box))
    if not ext.mask_files and not ext.boxes:
        raise ExternalError(
            f"{root}: no mask files named after cameras {cameras} (.h5/.npz) and no boxes.parquet"
        )
    return ext


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of a label image to (width, height)."""
    if (labels.shape[1], labels.shape[0]) == tuple(size):
        return labels
    return cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)


def boxes_to_labels(
    fg: np.ndarray | None,
    boxes: list[tuple[int, np.ndarray]],
    size: tuple[int, int],
    scale: tuple[float, float],
    min_fill: float = 0.2,
) -> np.ndarray:
    """Label image from boxes (full-resolution pixel edges): each box's foreground pixels, or the
    whole box when the background model sees too little of it (someone standing still).

    Later boxes do not overwrite earlier ones; boxes are drawn largest first.
    """
    w, h = size
    out = np.zeros((h, w), dtype=np.uint8)
    order = sorted(
        range(len(boxes)),
        key=lambda i: -(boxes[i][1][2] - boxes[i][1][0]) * (boxes[i][1][3] - boxes[i][1][1]),
    )
    for label, i in enumerate(order[:254], start=1):
        # Edges in pixel-centre coordinates (x = -0.5 is the image's left edge) to work columns.
        x0, y0, x1, y1 = boxes[i][1] + 0.5
        c0, r0 = (
            max(0, int(np.floor(x0 * scale[0] + 1e-9))),
            max(0, int(np.floor(y0 * scale[1] + 1e-9))),
        )
        c1, r1 = (
            min(w, int(np.ceil(x1 * scale[0] - 1e-9))),
            min(h, int(np.ceil(y1 * scale[1] - 1e-9))),
        )
        if c1 <= c0 or r1 <= r0:
            continue
        region = out[r0:r1, c0:c1]
        free = region == 0
        if fg is not None:
            inside = fg[r0:r1, c0:c1] > 0
            if inside.mean() >= min_fill:
                free &= inside
        region[free] = label
    return out
