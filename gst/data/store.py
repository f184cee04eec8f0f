"""The crop store: one HDF5 file per scene plus a Parquet index next to it.

Layout (format: docs/formats/crops_h5.md). Every per-crop dataset has N rows and is chunked and
compressed; rows beyond the root attribute `n_committed` are an unfinished batch and are
ignored by readers and cut off by the writer when it resumes. The pairs (frame, camera) that
have been fully processed, including those that produced no crop, are listed in `done`, so a
resumed run skips them. The attribute `complete` is set only after the last batch and the
Parquet index are written; `CropStore` refuses an incomplete store unless asked.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gst.atomic import atomic_path

log = logging.getLogger(__name__)

FORMAT = "gst-crops"
# 2: single_view per crop, optional landmarks; 3: with landmarks, whether they were projected
# from the rig's skeleton rather than read (older stores read as before)
VERSION = 3
N_LANDMARKS = 33
OPTIONAL_ROWS = ("landmarks", "landmarks_projected", "single_view")  # absent from older stores


# name -> (per-row shape given crop size S, dtype)
def _row_specs(size: int, landmarks: bool = False) -> dict[str, tuple[tuple[int, ...], str]]:
    specs = {
        "images": ((size, size, 3), "uint8"),
        "masks": ((size, size), "uint8"),
        "K_crop": ((3, 3), "float64"),
        "R": ((3, 3), "float64"),
        "t": ((3,), "float64"),
        "box": ((4,), "float64"),
        "crop_box": ((3,), "float64"),
        "camera": ((), "int32"),
        "frame": ((), "int64"),
        "person_id": ((), "int64"),
        "mask_support": ((), "float32"),
        "single_view": ((), "bool"),
    }
    if landmarks:
        specs["landmarks"] = ((N_LANDMARKS, 3), "float32")
        specs["landmarks_projected"] = ((), "bool")
    return specs


# datasets every readable store has (the oldest version-1 stores lack mask_support)
_REQUIRED = (*(k for k in _row_specs(1) if k not in OPTIONAL_ROWS), "camera_names", "done")
# the Parquet index's columns (docs/formats/crops_h5.md), in order
INDEX_COLUMNS = (
    "row", "frame", "camera", "camera_index", "person_id", "x0", "y0", "x1", "y1", "crop_x0",
    "crop_y0", "crop_side", "mask_coverage", "mask_support", "single_view",
)  # fmt: skip


class StoreError(ValueError):
    """A crop store is missing, incomplete, or was written with other settings."""


@dataclass
class CropBatch:
    """Rows to append (all arrays share the first dimension) or rows read back."""

    images: np.ndarray  # (n, S, S, 3) uint8, BGR as OpenCV decodes (see `rgb`)
    masks: np.ndarray  # (n, S, S) uint8 coverage, 255 = person
    K_crop: np.ndarray  # (n, 3, 3)
    R: np.ndarray  # (n, 3, 3) world to camera
    t: np.ndarray  # (n, 3) metres
    box: np.ndarray  # (n, 4) person box x0, y0, x1, y1 (edges) in the undistorted full image
    crop_box: np.ndarray  # (n, 3) crop square x0, y0, side (edges) in the undistorted full image
    camera: np.ndarray  # (n,) index into the store's camera names
    frame: np.ndarray  # (n,)
    person_id: np.ndarray  # (n,)
    mask_support: (
        np.ndarray
    )  # (n,) share of the person's 3D-hull footprint its mask covers (NaN: unknown)
    # (n,) bool: only one camera saw this person in this frame (None: False for every row)
    single_view: np.ndarray | None = None
    # (n, 33, 3) float32 BlazePose landmarks: u, v in crop pixels, confidence (None: not known)
    landmarks: np.ndarray | None = None
    # (n,) bool: the landmarks are the rig's skeleton projected into this view, not read from
    # its pixels (the landmark model did not confirm the person there); None: all read
    landmarks_projected: np.ndarray | None = None

    def __post_init__(self):
        if self.single_view is None:
            self.single_view = np.zeros(len(self.frame), bool)
        if self.landmarks is not None and self.landmarks_projected is None:
            self.landmarks_projected = np.zeros(len(self.frame), bool)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def rgb(self) -> np.ndarray:
        return self.images[..., ::-1]

    @staticmethod
    def concat(batches: list[CropBatch]) -> CropBatch:
        out = {}
        for k in CropBatch.__dataclass_fields__:
            parts = [getattr(b, k) for b in batches]
            if k in ("landmarks", "landmarks_projected") and any(p is None for p in parts):
                if any(p is not None for p in parts):
                    raise StoreError("cannot join crop batches with and without landmarks")
                out[k] = None
                continue
            out[k] = np.concatenate(parts)
        return CropBatch(**out)

    @staticmethod
    def empty(size: int, landmarks: bool = False) -> CropBatch:
        return CropBatch(
            **{
                k: np.zeros((0, *shape), dtype=dt)
                for k, (shape, dt) in _row_specs(size, landmarks).items()
            }
        )


class CropStoreWriter:
    """Appends crop batches to a store, creating it or resuming it.

    Use as a context manager. A store written with a different crop size, scale or camera list
    is an error (not silently mixed). `commit(batch, done_pairs)` makes a batch and the
    (frame, camera) pairs it finishes visible atomically with respect to readers and resumes.
    """

    def __init__(
        self,
        path: Path | str,
        camera_names: list[str],
        crop_size: int,
        settings: dict | None = None,
        compression: str = "gzip",
        compression_level: int = 1,
        landmarks: bool = False,
    ):
        self.path = Path(path)
        self.landmarks = bool(landmarks)  # the store holds per-crop landmarks
        self.camera_names = list(camera_names)
        self.crop_size = int(crop_size)
        self.settings = dict(settings or {})
        self.compression = compression
        self.compression_level = compression_level
        self._h5: h5py.File | None = None

    def __enter__(self) -> CropStoreWriter:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.path.exists():
            # created whole under a temporary name, then renamed: a kill while HDF5 wrote a new
            # file's first bytes left a file it could not open ("truncated file: eof = 96")
            with atomic_path(self.path, unique=False) as tmp:
                self._h5 = h5py.File(tmp, "w")
                try:
                    self._create()
                finally:
                    self.close()
        try:
            self._h5 = h5py.File(self.path, "a")
        except OSError as exc:
            text = str(exc)
            if getattr(exc, "errno", None) == 11 or "lock file" in text or "already open" in text:
                # a healthy store that a reader holds open: deleting it is wrong advice
                raise StoreError(
                    f"{self.path}: the store is open elsewhere ({exc}); close it (a notebook, a "
                    "report, a data loader) and run again"
                ) from exc
            raise StoreError(
                f"{self.path}: cannot open as HDF5 for appending ({exc}); "
                "delete it or choose another path"
            ) from exc
        f = self._h5
        try:
            fmt = f.attrs.get("format")
            if fmt is None and not len(f.keys()) and not len(f.attrs):
                self._create()  # new (empty) file
            elif fmt != FORMAT:
                raise StoreError(
                    f"{self.path}: exists and is not a crop store (format {fmt!r}); "
                    "refusing to overwrite it"
                )
            elif "n_committed" not in f.attrs:
                self._create()  # creation was interrupted before anything was committed
            else:
                self._check_compatible()
                self._truncate_to_committed()
        except Exception:
            self.close()
            raise

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    # -- creation and resume --------------------------------------------------------------------
    def _create(self) -> None:
        f = self._h5
        for name in list(f.keys()):
            del f[name]
        # the format first: a creation killed half-way is recognised as ours and created again
        # (n_committed, written last, is what marks a usable store)
        f.attrs["format"] = FORMAT
        S = self.crop_size
        opts = {}
        if self.compression == "gzip":
            opts = {"compression": "gzip", "compression_opts": self.compression_level}
        elif self.compression == "lzf":
            opts = {"compression": "lzf"}
        elif self.compression != "none":
            raise StoreError(
                f"compression '{self.compression}' is unknown; expected gzip, lzf or none"
            )
        for name, (shape, dtype) in _row_specs(S, self.landmarks).items():
            big = name in ("images", "masks")
            # Images and masks: a chunk per row, compressed; each commit only adds chunks. The
            # small per-row arrays share 1024-row chunks that every commit rewrites: compressed,
            # a rewritten chunk moved and HDF5 could give its old space to another chunk of the
            # same commit, so a kill mid-commit left committed rows unreadable ("filter returned
            # failure during read": 4 of 25 random kills, 8 of 16 kill points in the test) and
            # the store beyond resuming. Uncompressed, a chunk is rewritten in place, committed
            # rows with the same bytes (0 of 120 random kills).
            f.create_dataset(
                name,
                shape=(0, *shape),
                maxshape=(None, *shape),
                dtype=dtype,
                chunks=(1 if big else 1024, *shape),
                **(opts if big else {}),
            )
        f.create_dataset("done", shape=(0, 2), maxshape=(None, 2), dtype="int64", chunks=(4096, 2))
        f.create_dataset(
            "camera_names", data=np.array(self.camera_names, dtype=h5py.string_dtype())
        )
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        f.attrs["crop_size"] = S
        for key, value in self.settings.items():
            f.attrs[f"setting.{key}"] = value
        f.attrs["n_done"] = 0
        f.attrs["complete"] = False
        f.attrs["n_committed"] = 0  # written last: its presence marks a usable store
        f.flush()

    def _check_compatible(self) -> None:
        f = self._h5
        if f.attrs.get("format") != FORMAT:
            raise StoreError(
                f"{self.path}: not a crop store (format attribute {f.attrs.get('format')!r})"
            )
        version = int(f.attrs.get("version", 0))
        if version != VERSION:
            raise StoreError(
                f"{self.path}: crop store version {version}, this writer appends to version "
                f"{VERSION} only; use a new path or delete it"
            )
        if int(f.attrs["crop_size"]) != self.crop_size:
            raise StoreError(
                f"{self.path}: written with crop_size={int(f.attrs['crop_size'])}, "
                f"asked to append crop_size={self.crop_size}; use a new path or delete it"
            )
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["camera_names"][()]]
        if names != self.camera_names:
            raise StoreError(
                f"{self.path}: written for cameras {names}, asked to append for "
                f"{self.camera_names}; use a new path or delete it"
            )
        stored = {k[len("setting.") :] for k in f.attrs if k.startswith("setting.")}
        if stored != set(self.settings):
            # a setting on one side only was accepted unchecked (and never recorded)
            raise StoreError(
                f"{self.path}: written with settings {sorted(stored)}, asked to append with "
                f"{sorted(self.settings)}; use a new path or delete it"
            )
        for key, value in self.settings.items():
            old = f.attrs.get(f"setting.{key}")
            if old is not None and not np.array_equal(np.asarray(old), np.asarray(value)):
                raise StoreError(
                    f"{self.path}: written with {key}={old!r}, asked to append with "
                    f"{key}={value!r}; use a new path or delete it"
                )
        # after the settings: a changed setting (the association, hull -> keypoints, once the
        # person model is installed) is the cause to name, not the landmarks it brings
        if ("landmarks" in f) != self.landmarks:
            held = "holds" if "landmarks" in f else "has no"
            ours = "writes them" if self.landmarks else "has none"
            raise StoreError(
                f"{self.path}: {held} landmarks and this writer {ours} (the rows would not line "
                "up); use a new path or delete it"
            )
        missing = [k for k in _row_specs(self.crop_size, self.landmarks) if k not in f]
        if missing:
            raise StoreError(
                f"{self.path}: has no {missing} datasets (written by an older version or "
                "without landmarks); use a new path or delete it"
            )

    def _truncate_to_committed(self) -> None:
        f = self._h5
        n = int(f.attrs["n_committed"])
        for name in _row_specs(self.crop_size, self.landmarks):
            if f[name].shape[0] != n:
                f[name].resize(n, axis=0)
        n_done = int(f.attrs["n_done"])
        if f["done"].shape[0] != n_done:
            f["done"].resize(n_done, axis=0)
        f.attrs["complete"] = False
        f.flush()

    # -- appending ------------------------------------------------------------------------------
    @property
    def n_committed(self) -> int:
        return int(self._h5.attrs["n_committed"])

    def done_pairs(self) -> set[tuple[int, int]]:
        """(frame, camera index) pairs already processed."""
        d = self._h5["done"][: int(self._h5.attrs["n_done"])]
        return {(int(a), int(b)) for a, b in d}

    def commit(self, batch: CropBatch, done: list[tuple[int, int]] | np.ndarray) -> None:
        """Append `batch` and mark the (frame, camera index) pairs in `done` as processed."""
        f = self._h5
        n0 = self.n_committed
        n = len(batch)
        S = self.crop_size
        if n:
            if batch.images.shape[1:] != (S, S, 3) or batch.masks.shape[1:] != (S, S):
                raise StoreError(
                    f"{self.path}: batch crops are {batch.images.shape[1:]}, store holds {S}x{S}"
                )
            if self.landmarks and batch.landmarks is None:
                raise StoreError(f"{self.path}: the store holds landmarks, the batch has none")
            values = {}
            for name, (shape, _dt) in _row_specs(S, self.landmarks).items():
                value = getattr(batch, name)
                if name == "landmarks_projected" and value is None:  # all read
                    value = np.zeros(n, bool)
                # h5py broadcasts: a field of one row was copied to every row of the batch
                if np.shape(value) != (n, *shape):
                    raise StoreError(
                        f"{self.path}: batch field '{name}' has shape {np.shape(value)}, "
                        f"expected {(n, *shape)} ({n} rows)"
                    )
                # h5py casts silently: a person id of 1.7 was stored as 1
                if np.dtype(_dt).kind in "iub" and np.asarray(value).dtype.kind not in "iub":
                    raise StoreError(
                        f"{self.path}: batch field '{name}' holds {np.asarray(value).dtype} "
                        f"values, expected {_dt}"
                    )
                values[name] = value
            cams = np.asarray(values["camera"])
            if cams.min() < 0 or cams.max() >= len(self.camera_names):
                raise StoreError(
                    f"{self.path}: batch camera indices {cams.min()}..{cams.max()} outside the "
                    f"store's {len(self.camera_names)} cameras {self.camera_names}"
                )
            for name, value in values.items():
                ds = f[name]
                ds.resize(n0 + n, axis=0)
                ds[n0 : n0 + n] = value
        self._mark_done(done, n0 + n)

    def commit_rows(
        self, src: h5py.File, a: int, b: int, done: list[tuple[int, int]] | np.ndarray
    ) -> None:
        """`commit` of rows a..b-1 of another store's file (a part store written with the same
        settings). The crops and masks (one row per chunk) are copied as their compressed
        chunks, without decompressing and compressing them again, where both layouts agree."""
        f = self._h5
        n0, n = self.n_committed, b - a
        S = self.crop_size
        if n:
            if src["images"].shape[1:] != (S, S, 3):
                raise StoreError(
                    f"{src.filename}: crops are {src['images'].shape[1:]}, store holds {S}x{S}"
                )
            for name in _row_specs(S, self.landmarks):
                if name not in src:  # e.g. the store holds landmarks, the part none
                    raise StoreError(f"{src.filename}: has no '{name}' rows to copy")
                ds, part = f[name], src[name]
                ds.resize(n0 + n, axis=0)
                if _same_row_chunks(part, ds):
                    tail = (0,) * (ds.ndim - 1)
                    for r in range(n):
                        mask, chunk = part.id.read_direct_chunk((a + r, *tail))
                        ds.id.write_direct_chunk((n0 + r, *tail), chunk, mask)
                else:
                    ds[n0 : n0 + n] = part[a:b]
        self._mark_done(done, n0 + n)

    def _mark_done(self, done: list[tuple[int, int]] | np.ndarray, n_committed: int) -> None:
        f = self._h5
        done = np.asarray(done, dtype=np.int64).reshape(-1, 2)
        d0 = int(f.attrs["n_done"])
        if len(done):
            f["done"].resize(d0 + len(done), axis=0)
            f["done"][d0:] = done
        f.flush()  # data on disk before the counters that make it visible
        f.attrs["n_done"] = d0 + len(done)
        f.attrs["n_committed"] = n_committed
        f.flush()

    def finalize(self, extra_attrs: dict | None = None) -> Path:
        """Write the Parquet index (temporary file, then rename) and mark the store complete."""
        f = self._h5
        for key, value in (extra_attrs or {}).items():
            f.attrs[key] = value
        f.flush()
        index_path = write_index(f, self.path)
        f.attrs["complete"] = True
        f.flush()
        return index_path


def index_path_for(store_path: Path | str) -> Path:
    p = Path(store_path)
    return p.with_name(p.stem + ".index.parquet")


def _read_index_columns(f: h5py.File) -> dict[str, np.ndarray]:
    n = int(f.attrs["n_committed"])
    names = [x.decode() if isinstance(x, bytes) else str(x) for x in f["camera_names"][()]]
    cam = f["camera"][:n]
    box = f["box"][:n]
    crop = f["crop_box"][:n]
    masks_area = np.empty(n, dtype=np.float32)
    for i0 in range(0, n, 512):  # mask coverage, read in slabs to bound memory
        m = f["masks"][i0 : min(i0 + 512, n)]  # a half-written batch may lie beyond n
        masks_area[i0 : i0 + len(m)] = m.reshape(len(m), -1).mean(axis=1) / 255.0
    return {
        "row": np.arange(n, dtype=np.int64),
        "frame": f["frame"][:n],
        "camera": np.array(names, dtype=object)[cam] if n else np.zeros(0, dtype=object),
        "camera_index": cam,
        "person_id": f["person_id"][:n],
        "x0": box[:, 0],
        "y0": box[:, 1],
        "x1": box[:, 2],
        "y1": box[:, 3],
        "crop_x0": crop[:, 0],
        "crop_y0": crop[:, 1],
        "crop_side": crop[:, 2],
        "mask_coverage": masks_area,
        "mask_support": f["mask_support"][:n],
        "single_view": f["single_view"][:n] if "single_view" in f else np.zeros(n, bool),
    }


def _index_table(f: h5py.File) -> pa.Table:
    """The index columns of an open store as a table (camera names typed as strings even when
    there are no rows: an empty store's index had a null-typed column, so indices of several
    stores could not be joined)."""
    cols = _read_index_columns(f)
    if tuple(cols) != INDEX_COLUMNS:  # the list the reader checks an index against
        raise AssertionError(f"index columns {tuple(cols)} differ from INDEX_COLUMNS")
    return pa.table(
        {
            k: pa.array(v.tolist(), type=pa.string()) if k == "camera" else pa.array(v)
            for k, v in cols.items()
        }
    )


def write_index(f: h5py.File, store_path: Path) -> Path:
    """Write the Parquet index of the committed rows of an open store (atomically)."""
    table = _index_table(f).replace_schema_metadata(
        {
            "store": Path(store_path).name,
            "n_committed": str(int(f.attrs["n_committed"])),
            "crop_size": str(int(f.attrs["crop_size"])),
        }
    )
    out = index_path_for(store_path)
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return out


@dataclass(frozen=True)
class MultiViewGroup:
    """All crops of one person in one frame, at most one per camera."""

    frame: int
    person_id: int
    indices: np.ndarray  # store rows
    cameras: np.ndarray  # camera indices, same order


class CropStore:
    """Read-only access to a crop store. Safe to pickle (reopens the file lazily per process).

    `select` and `multiview_groups` use the Parquet index; `read` loads rows.
    """

    def __init__(self, path: Path | str, allow_incomplete: bool = False):
        self.path = Path(path)
        if not self.path.is_file():
            raise StoreError(f"crop store {self.path} does not exist")
        try:
            f = h5py.File(self.path, "r")
        except OSError as exc:  # truncated or not HDF5 at all: h5py's message names no file
            raise StoreError(f"{self.path}: cannot open the crop store ({exc})") from exc
        with f:
            if f.attrs.get("format") != FORMAT or "n_committed" not in f.attrs:
                raise StoreError(f"{self.path}: not a crop store")
            version = int(f.attrs.get("version", 0))
            if not 1 <= version <= VERSION:
                raise StoreError(
                    f"{self.path}: crop store version {version}; this code reads versions 1 to "
                    f"{VERSION}{' (update the package)' if version > VERSION else ''}"
                )
            if not bool(f.attrs.get("complete")) and not allow_incomplete:
                raise StoreError(
                    f"{self.path}: the store is incomplete (its writer did not finish); "
                    "rerun the extraction to resume it, or pass allow_incomplete=True"
                )
            missing = [k for k in _REQUIRED if k not in f]
            if missing:
                raise StoreError(
                    f"{self.path}: crop store without its {', '.join(missing)} dataset(s) "
                    "(damaged, or written before they existed); extract again"
                )
            self.n = int(f.attrs["n_committed"])
            # a row dataset shorter than the committed rows (a damaged file) was read as
            # complete: the index failed on it naming no file, `read` with "Fancy indexing
            # out of range", and a short `masks` left unset mask coverages in the index
            short = [
                f"{k} ({f[k].shape[0]})"
                for k in _row_specs(1, True)
                if k in f and f[k].shape[0] < self.n
            ]
            if int(f.attrs.get("n_done", 0)) > f["done"].shape[0]:
                short.append(f"done ({f['done'].shape[0]} of n_done {int(f.attrs['n_done'])})")
            if short:
                raise StoreError(
                    f"{self.path}: damaged crop store: {self.n} committed rows, but dataset(s) "
                    f"{', '.join(short)} hold fewer; extract again"
                )
            self.crop_size = int(f.attrs["crop_size"])
            self.camera_names = [
                x.decode() if isinstance(x, bytes) else str(x) for x in f["camera_names"][()]
            ]
            self.attrs = {k: f.attrs[k] for k in f.attrs}
            self.index = self._load_index(f)
        self._h5: h5py.File | None = None

    def _load_index(self, f: h5py.File) -> pa.Table:
        """The Parquet index if it describes this file's rows, else one rebuilt in memory (a
        missing index, an incomplete store's, a damaged file, an older version's columns, or
        another store's: a crops.h5 copied without its index, or over another's, had its
        pixels read under the other's frames and people when the row counts agreed)."""
        ip = index_path_for(self.path)
        if not ip.is_file():
            return _index_table(f)
        try:
            table = pq.read_table(ip)
        except (pa.ArrowException, OSError) as exc:
            log.warning("%s: index unreadable (%s); rebuilt from the store", ip, exc)
            return _index_table(f)
        n = self.n
        fresh = (
            table.num_rows == n
            and set(INDEX_COLUMNS) <= set(table.column_names)
            and all(
                np.array_equal(table.column(col).to_numpy(), f[ds][:n])
                for col, ds in (
                    ("frame", "frame"),
                    ("camera_index", "camera"),
                    ("person_id", "person_id"),
                )  # fmt: skip
            )
            # the same rows cut at another scale: their boxes differ
            and np.array_equal(
                np.stack(
                    [table.column(c).to_numpy() for c in ("crop_x0", "crop_y0", "crop_side")], 1
                ),
                f["crop_box"][:n],
            )
        )
        if not fresh:  # another store's, of any length (a crops.h5 copied over another's)
            log.warning("%s: index does not describe %s's rows; rebuilt", ip, self.path.name)
        return table if fresh else _index_table(f)

    def __len__(self) -> int:
        return self.n

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_h5"] = None
        return state

    def _file(self) -> h5py.File:
        if self._h5 is None:
            self._h5 = h5py.File(self.path, "r")
        return self._h5

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def _column(self, name: str) -> np.ndarray:
        return self.index.column(name).to_numpy()

    def _camera_indices(self, cameras) -> list[int]:
        out = []
        for c in cameras:
            if isinstance(c, str):
                if c not in self.camera_names:
                    raise KeyError(
                        f"camera '{c}' is not in store {self.path} (cameras: {self.camera_names})"
                    )
                out.append(self.camera_names.index(c))
            else:
                out.append(int(c))
        return out

    def select(self, frames=None, cameras=None, persons=None) -> np.ndarray:
        """Rows matching all given filters (each an iterable; cameras by name or index)."""
        keep = np.ones(self.n, dtype=bool)
        if frames is not None:
            keep &= np.isin(self._column("frame"), np.asarray(list(frames), dtype=np.int64))
        if cameras is not None:
            keep &= np.isin(self._column("camera_index"), self._camera_indices(cameras))
        if persons is not None:
            keep &= np.isin(self._column("person_id"), np.asarray(list(persons), dtype=np.int64))
        return np.nonzero(keep)[0]

    def multiview_groups(self, min_views: int = 2) -> list[MultiViewGroup]:
        """Per (frame, person): the rows from different cameras, if at least `min_views`."""
        frame = self._column("frame")
        person = self._column("person_id")
        cam = self._column("camera_index")
        order = np.lexsort((cam, person, frame))
        groups = []
        if len(order) == 0:
            return groups
        key = np.stack([frame[order], person[order]], axis=1)
        starts = np.concatenate(
            [[0], np.nonzero(np.any(key[1:] != key[:-1], axis=1))[0] + 1, [len(order)]]
        )
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            rows = order[a:b]
            # One crop per camera (the writer guarantees it; keep the first if not).
            _, first = np.unique(cam[rows], return_index=True)
            rows = rows[np.sort(first)]
            if len(rows) >= min_views:
                groups.append(
                    MultiViewGroup(int(frame[rows[0]]), int(person[rows[0]]), rows, cam[rows])
                )
        return groups

    def read_landmarks(self, rows=None) -> np.ndarray | None:
        """(n, 33, 3) float32 landmarks of `rows` (default all, in the given order), or None
        when the store holds none; no image is read."""
        f = self._file()
        if "landmarks" not in f:
            return None
        if rows is None:
            return np.asarray(f["landmarks"][: self.n], np.float32)
        return _read_rows(f["landmarks"], self._rows(rows)).astype(np.float32, copy=False)

    def read_landmarks_projected(self, rows=None) -> np.ndarray | None:
        """(n,) bool of `rows` (default all): the crop's landmarks are the rig's skeleton
        projected into the view, not a reading of its pixels; None when the store does not say
        (no landmarks, or written before version 3)."""
        if "landmarks_projected" not in self._file():
            return None
        return self.read_column("landmarks_projected", rows).astype(bool, copy=False)

    def read_masks(self, rows=None) -> np.ndarray:
        """(n, S, S) uint8 person masks of `rows` (default all, in the given order); no image
        is read."""
        return self.read_column("masks", rows)

    def read_images(self, rows=None) -> np.ndarray:
        """(n, S, S, 3) uint8 BGR crops of `rows` (default all, in the given order); nothing
        else is read."""
        return self.read_column("images", rows)

    def read_column(self, name: str, rows=None) -> np.ndarray:
        """One dataset's values of `rows` (default all, in the given order), e.g. `K_crop`."""
        f = self._file()
        if rows is None:
            return np.asarray(f[name][: self.n])
        return _read_rows(f[name], self._rows(rows))

    def _rows(self, rows) -> np.ndarray:
        """`rows` as int64, each a committed row: rows past `n_committed` (a half-written
        batch) and negative rows (counted from the dataset's physical end) were read as data."""
        rows = np.asarray(rows)
        if rows.dtype == bool:  # True/False were read as rows 1 and 0
            if rows.shape != (self.n,):
                raise IndexError(
                    f"{self.path}: a boolean row mask must have one value per row ({self.n}), "
                    f"got shape {rows.shape}"
                )
            rows = np.flatnonzero(rows)
        rows = rows.astype(np.int64).reshape(-1)
        if len(rows) and (rows.min() < 0 or rows.max() >= self.n):
            raise IndexError(
                f"{self.path}: rows must be in [0, {self.n}), got {rows.min()}..{rows.max()}"
            )
        return rows

    def read(self, rows) -> CropBatch:
        """Load the given rows (any order; returned in that order)."""
        rows = self._rows(rows)
        f = self._file()
        out = {
            name: _read_rows(f[name], rows)
            for name in CropBatch.__dataclass_fields__
            if name not in OPTIONAL_ROWS or name in f  # a version 1 store, or no landmarks
        }
        return CropBatch(**out)


def _read_rows(dataset: h5py.Dataset, rows) -> np.ndarray:
    """`dataset[rows]` for any order and repeats (HDF5 reads want increasing unique rows)."""
    rows = np.asarray(rows, np.int64).reshape(-1)
    order = np.argsort(rows, kind="stable")
    uniq, inv = np.unique(rows[order], return_inverse=True)
    data = np.asarray(dataset[uniq] if len(uniq) else dataset[:0])
    out = np.empty((len(rows), *dataset.shape[1:]), data.dtype)
    out[order] = data[inv]
    return out


def _same_row_chunks(a: h5py.Dataset, b: h5py.Dataset) -> bool:
    """Whether two datasets store one row per chunk with the same type and filters, so a
    compressed chunk of one is a valid chunk of the other."""
    return (
        a.chunks is not None
        and a.chunks[0] == 1
        and a.chunks == b.chunks
        and a.dtype == b.dtype
        and a.compression == b.compression
        and a.compression_opts == b.compression_opts
        and a.shuffle == b.shuffle
        and a.fletcher32 == b.fletcher32
        and a.scaleoffset == b.scaleoffset
    )


def merge_part(
    writer: CropStoreWriter, part_path: Path, camera_index: int, commit_frames: int
) -> int:
    """Append a camera's part store to the scene store, frame chunk by frame chunk; returns the
    number of (frame, camera) pairs added."""
    if commit_frames < 1:
        raise StoreError(f"merge_part: commit_frames must be at least 1, got {commit_frames}")
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
            a = b = 0
            if len(rows):
                a, b = int(rows.min()), int(rows.max()) + 1
                if b - a != len(rows):
                    raise StoreError(
                        f"{part_path}: rows of frames {chunk[0]}..{chunk[-1]} are not contiguous"
                    )
            writer.commit_rows(f, a, b, [(fr, camera_index) for fr in chunk])
            added += len(chunk)
    return added


_WRITER_ATTRS = ("format", "version", "crop_size", "n_done", "complete", "n_committed")


def write_subset(store: CropStore, rows, out: Path | str, chunk: int = 256) -> CropStore:
    """A complete store at `out` holding only `rows` of `store`, in that order, with the same
    crop size, cameras, settings and attributes; the (frame, camera) pairs of `store` that none
    of the other rows falls in are marked processed. For a fusion that must not see the rest
    (the rig teacher without held-out cameras and frames: gst.lift.teacher)."""
    rows = store._rows(rows)  # checked before anything is written
    out = Path(out)
    # the old store and its index are deleted before the copy is read from it
    if out.resolve() == Path(store.path).resolve():
        raise StoreError(f"{out}: a subset cannot be written over the store it is taken from")
    settings, extra = {}, {}
    for k, v in store.attrs.items():
        if k.startswith("setting."):
            settings[k[len("setting.") :]] = v
        elif k not in _WRITER_ATTRS:
            extra[k] = v
    with h5py.File(store.path, "r") as f:
        done = f["done"][: int(f.attrs["n_done"])]
    frame, camera = store._column("frame"), store._column("camera_index")
    left_out = np.ones(len(store), bool)
    left_out[rows] = False
    gone = set(zip(frame[left_out].tolist(), camera[left_out].tolist(), strict=True))
    done = [tuple(p) for p in done.tolist() if tuple(p) not in gone]
    has_landmarks = store.read_landmarks(np.zeros(0, np.int64)) is not None
    for p in (out, index_path_for(out)):
        p.unlink(missing_ok=True)
    with (
        h5py.File(store.path, "r") as src,
        CropStoreWriter(out, store.camera_names, store.crop_size, settings,
                        landmarks=has_landmarks) as w,
    ):  # fmt: skip
        if all(name in src for name in _row_specs(store.crop_size, has_landmarks)):
            # runs of consecutive rows, their compressed crops copied as they are
            for run in np.split(rows, np.flatnonzero(np.diff(rows) != 1) + 1):
                if len(run):
                    w.commit_rows(src, int(run[0]), int(run[-1]) + 1, [])
        else:  # an older store without some rows' columns: through the reader
            for a in range(0, len(rows), chunk):
                w.commit(store.read(rows[a : a + chunk]), [])
        w.commit(CropBatch.empty(store.crop_size, has_landmarks), done)
        w.finalize(extra)
    return CropStore(out)
